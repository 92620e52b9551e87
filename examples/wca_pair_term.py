"""A user-written pair term: Weeks-Chandler-Andersen repulsion on the pair frame.

WCA is Lennard-Jones cut at its minimum, r_c = 2^(1/6) sigma, and shifted up
by epsilon, so it is purely repulsive and continuous with its force at the
cutoff. Ten lines of pair term give it everything the built-in potentials
have: neighbour lists, threads, the vectorised pair loop, the virial,
triclinic cells, the ASE calculator and (with its curvature) implicit Euler.

    PYTHONPATH=. python3 examples/wca_pair_term.py
"""

from __future__ import annotations

import md
from integrators import ImplicitEuler, VelocityVerlet
from potentials import PairPotential, pair_term


@pair_term
def wca(r2, epsilon, sigma):
    """u = 4 eps [(s/r)^12 - (s/r)^6] + eps and -u'(r)/r (the frame cuts it at 2^(1/6) s)."""
    x6 = (sigma * sigma / r2) ** 3
    return 4.0 * epsilon * (x6 * x6 - x6) + epsilon, 24.0 * epsilon * (2.0 * x6 * x6 - x6) / r2


@wca.with_curvature
def wca_curvature(r2, epsilon, sigma):
    """u and its derivatives in s = r^2 (for Hessians: implicit integrators)."""
    x6 = (sigma * sigma / r2) ** 3
    u = 4.0 * epsilon * (x6 * x6 - x6) + epsilon
    du_ds = 12.0 * epsilon * (x6 - 2.0 * x6 * x6) / r2
    return u, du_ds, 24.0 * epsilon * (7.0 * x6 * x6 - 2.0 * x6) / (r2 * r2)


def make_potential(epsilon: float = 1.0, sigma: float = 1.0) -> PairPotential:
    """WCA as a pair potential: truncated (no shift) at 2^(1/6) sigma."""
    return PairPotential(
        wca, epsilon=epsilon, sigma=sigma, cutoff=2 ** (1 / 6) * sigma, cutoff_mode="none"
    )


def main() -> None:
    state = md.maxwell_boltzmann(md.lattice("fcc", 6, density=0.8), 1.0, seed=1)
    sim = md.Simulation(state, [make_potential()], VelocityVerlet(0.004))
    start = sim.thermo()["total_energy"]
    sim.run(500)
    thermo = sim.thermo()
    drift = (thermo["total_energy"] - start) / state.n_atoms
    print(
        f"WCA fluid, {state.n_atoms} atoms, 500 steps of velocity Verlet: "
        f"T = {thermo['temperature']:.3f}, P = {thermo['pressure']:.3f}, "
        f"energy drift {drift:+.2e} per atom"
    )
    implicit = md.Simulation(state, [make_potential()], ImplicitEuler(0.004))
    implicit.run(20)
    print(
        f"20 implicit Euler steps (Newton, with the term's curvature): "
        f"T = {implicit.thermo()['temperature']:.3f}"
    )


if __name__ == "__main__":
    main()
