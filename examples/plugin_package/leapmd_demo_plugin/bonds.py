"""An anharmonic bond style on leapmd's bonded frame, as the built-in styles are written."""

from potentials import BondPotential, bond_term


def anharmonic_energy(r, k, r0, c):
    """u = k/2 d^2 + c d^4 and du/dr, d = r - r0."""
    d = r - r0
    return 0.5 * k * d * d + c * d**4, k * d + 4.0 * c * d**3


ANHARMONIC = bond_term(anharmonic_energy, name="demo_anharmonic")


class AnharmonicBonds(BondPotential):
    """Anharmonic bonds u(r) = k/2 (r - r0)^2 + c (r - r0)^4 over listed bonds.

    It declares no CONFIG_KEYS: its keys are bonds (or bonds_file), bond_types and its
    constructor's parameters, with the constructor's defaults.
    """

    def __init__(self, bonds, k=10.0, r0=1.0, c=0.0, bond_types=None):
        super().__init__(ANHARMONIC, bonds, bond_types, k=k, r0=r0, c=c)
