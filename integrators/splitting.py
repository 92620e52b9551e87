"""Symplectic splitting methods as one framework: a table of kick and drift coefficients.

Newton's equations x' = v, v' = f(x)/m split into a drift (x += c dt v,
exact for the kinetic part) and a kick (v += c dt f/m, exact for the
potential part). A splitting method is a palindrome of drifts and kicks
whose coefficients each sum to one; being a composition of exact flows of
Hamiltonian parts, every such method is symplectic, and being symmetric it is
time-reversible, whatever the coefficients. The coefficients decide the
order (the number of conditions of the Baker-Campbell-Hausdorff expansion
they satisfy) and the error constant.

One class, :class:`Splitting`, steps through any table with the two kernels
of ``integrators._kernels``; the named methods below are tables:

===================  =====  ======  ===================================================
name                 order  forces  coefficients
===================  =====  ======  ===================================================
``yoshida4``         4      3       Forest and Ruth (1990) / Yoshida (1990): velocity
                                    Verlet composed with weights w1, w0, w1,
                                    w1 = 1 / (2 - 2^(1/3)), w0 = 1 - 2 w1
``yoshida6``         6      7       Yoshida (1990), solution A: seven velocity Verlet
                                    substeps (w3, w2, w1, w0, w1, w2, w3)
``pefrl``            4      4       Omelyan, Mryglod and Folk, Comput. Phys. Commun.
                                    146, 188 (2002): position-extended Forest-Ruth-like,
                                    optimised error constant
``blanes_moan``      4      6       Blanes and Moan, J. Comput. Appl. Math. 142, 313
                                    (2002): the optimised 6-stage partitioned RK
                                    method (drift first)
``blanes_moan_rkn``  4      6       the same paper's optimised 6-stage
                                    Runge-Kutta-Nystrom method (kick first)
===================  =====  ======  ===================================================

"forces" counts force evaluations per step: a method that starts and ends
with a kick reuses the last kick's forces at the start of the next step
(the force field's cache does this by itself). The orders are measured,
not assumed: ``tests/test_splitting.py`` fits them, and checks time
reversibility and the symplectic form of one step's Jacobian.
"""

from __future__ import annotations

import math

from integrators._kernels import _drift, kick
from integrators.base import IntegratorBase, check_dt

KICK, DRIFT = 0, 1


def compose(weights) -> list[tuple[int, float]]:
    """The kick/drift table of velocity Verlet substeps of the given relative lengths.

    Adjacent kicks of consecutive substeps merge into one.

    Examples
    --------
    >>> compose([1.0])
    [(0, 0.5), (1, 1.0), (0, 0.5)]
    """
    table: list[tuple[int, float]] = []
    for w in weights:
        if table and table[-1][0] == KICK:
            table[-1] = (KICK, table[-1][1] + 0.5 * w)
        else:
            table.append((KICK, 0.5 * w))
        table += [(DRIFT, w), (KICK, 0.5 * w)]
    return table


def alternate(first: int, coefficients) -> list[tuple[int, float]]:
    """A table alternating kicks and drifts, starting with ``first`` (KICK or DRIFT)."""
    kinds = (first, DRIFT if first == KICK else KICK)
    return [(kinds[k % 2], float(c)) for k, c in enumerate(coefficients)]


_CBRT2 = 2.0 ** (1.0 / 3.0)
_Y4 = 1.0 / (2.0 - _CBRT2)
_Y6 = (-1.17767998417887, 0.235573213359357, 0.784513610477560)
_Y6_W0 = 1.0 - 2.0 * sum(_Y6)

_XI, _LAMBDA, _CHI = 0.1786178958448091, -0.2123418310626054, -0.06626458266981849

_BM_A = (0.0792036964311957, 0.353172906049774, -0.0420650803577195)
_BM_B = (0.209515106613362, -0.143851773179818)
_BM_RKN_B = (0.0829844064174052, 0.396309801498368, -0.0390563049223486)
_BM_RKN_A = (0.245298957184271, 0.604872665711080)

#: Name -> (table, order, reference): the coefficient tables of the named methods.
METHODS = {
    "yoshida4": (
        compose([_Y4, 1.0 - 2.0 * _Y4, _Y4]),
        4,
        "E. Forest, R. D. Ruth, Physica D 43, 105 (1990); H. Yoshida, Phys. Lett. A 150, "
        "262 (1990)",
    ),
    "yoshida6": (
        compose([_Y6[2], _Y6[1], _Y6[0], _Y6_W0, _Y6[0], _Y6[1], _Y6[2]]),
        6,
        "H. Yoshida, Phys. Lett. A 150, 262 (1990), solution A",
    ),
    "pefrl": (
        alternate(
            DRIFT,
            [
                _XI,
                0.5 * (1.0 - 2.0 * _LAMBDA),
                _CHI,
                _LAMBDA,
                1.0 - 2.0 * (_CHI + _XI),
                _LAMBDA,
                _CHI,
                0.5 * (1.0 - 2.0 * _LAMBDA),
                _XI,
            ],
        ),
        4,
        "I. P. Omelyan, I. M. Mryglod, R. Folk, Comput. Phys. Commun. 146, 188 (2002)",
    ),
    "blanes_moan": (
        alternate(
            DRIFT,
            [
                _BM_A[0],
                _BM_B[0],
                _BM_A[1],
                _BM_B[1],
                _BM_A[2],
                0.5 - sum(_BM_B),
                1.0 - 2.0 * sum(_BM_A),
                0.5 - sum(_BM_B),
                _BM_A[2],
                _BM_B[1],
                _BM_A[1],
                _BM_B[0],
                _BM_A[0],
            ],
        ),
        4,
        "S. Blanes, P. C. Moan, J. Comput. Appl. Math. 142, 313 (2002), PRK method S6",
    ),
    "blanes_moan_rkn": (
        alternate(
            KICK,
            [
                _BM_RKN_B[0],
                _BM_RKN_A[0],
                _BM_RKN_B[1],
                _BM_RKN_A[1],
                _BM_RKN_B[2],
                0.5 - sum(_BM_RKN_A),
                1.0 - 2.0 * sum(_BM_RKN_B),
                0.5 - sum(_BM_RKN_A),
                _BM_RKN_B[2],
                _BM_RKN_A[1],
                _BM_RKN_B[1],
                _BM_RKN_A[0],
                _BM_RKN_B[0],
            ],
        ),
        4,
        "S. Blanes, P. C. Moan, J. Comput. Appl. Math. 142, 313 (2002), RKN method SRKN6b",
    ),
}


class Splitting(IntegratorBase):
    """A symmetric kick/drift splitting method given by its coefficient table.

    Parameters
    ----------
    dt : float
        Time step [time].
    table : sequence of (kind, coefficient)
        ``kind`` is :data:`KICK` (v += c dt f/m) or :data:`DRIFT`
        (x += c dt v); the kick coefficients and the drift coefficients
        must each sum to one and the table must read the same both ways.
    name : str
        Name used in descriptions.

    Raises
    ------
    ValueError
        If the table is empty, not symmetric, or its coefficients do not sum to one.

    Examples
    --------
    >>> verlet = Splitting(0.01, [(KICK, 0.5), (DRIFT, 1.0), (KICK, 0.5)], name="verlet")
    >>> verlet.force_evaluations
    1
    """

    #: The method's order (None: not one of the named tables).
    order: int | None = None
    distributed = True

    def __init__(self, dt: float, table, name: str = "splitting") -> None:
        self.dt = check_dt(dt)
        self.table = [(int(kind), float(c)) for kind, c in table]
        self.name = name
        _check_table(self.table)

    @property
    def force_evaluations(self) -> int:
        """Force evaluations per step (a last kick's forces serve the next step's first)."""
        kicks = sum(1 for kind, _ in self.table if kind == KICK)
        reused = self.table[0][0] == KICK and self.table[-1][0] == KICK
        return kicks - int(reused)

    def step(self, state, forcefield) -> None:
        inverse_masses = 1.0 / state.masses
        dt = self.dt
        for kind, c in self.table:
            if kind == KICK:
                forces = forcefield.compute(state, virial=False).forces
                kick(state.velocities, forces, inverse_masses, c * dt)
            else:
                _drift(state.positions, state.velocities, c * dt)
        self.end_step(state)

    def describe(self) -> dict:
        return {"type": self.name, "dt": self.dt}


def _check_table(table) -> None:
    if not table:
        raise ValueError("a splitting table needs at least one kick and one drift")
    for kind, c in table:
        if kind not in (KICK, DRIFT) or not math.isfinite(c):
            raise ValueError(f"bad table entry ({kind}, {c}): kind must be KICK or DRIFT")
    for kind, label in ((KICK, "kick"), (DRIFT, "drift")):
        total = sum(c for k, c in table if k == kind)
        if abs(total - 1.0) > 1e-12:
            raise ValueError(f"the {label} coefficients sum to {total!r}, not 1")
    for (k1, c1), (k2, c2) in zip(table, reversed(table), strict=True):
        if k1 != k2 or abs(c1 - c2) > 1e-12:
            raise ValueError("the table is not symmetric (a palindrome): not time-reversible")


def _named(method: str, doc: str):
    table, order, reference = METHODS[method]

    class Named(Splitting):
        def __init__(self, dt: float) -> None:
            super().__init__(dt, table, name=method)

    Named.order = order
    Named.reference = reference
    Named.__doc__ = f"{doc}\n\n    Order {order}; {reference}.\n"
    return Named


Yoshida4 = _named("yoshida4", "Fourth-order triple-jump composition of velocity Verlet.")
Yoshida4.__name__ = Yoshida4.__qualname__ = "Yoshida4"
Yoshida6 = _named("yoshida6", "Sixth-order composition of seven velocity Verlet substeps.")
Yoshida6.__name__ = Yoshida6.__qualname__ = "Yoshida6"
PEFRL = _named("pefrl", "Omelyan-Mryglod-Folk optimised fourth-order splitting (4 forces).")
PEFRL.__name__ = PEFRL.__qualname__ = "PEFRL"
BlanesMoan = _named("blanes_moan", "Blanes-Moan optimised fourth-order PRK splitting (6 forces).")
BlanesMoan.__name__ = BlanesMoan.__qualname__ = "BlanesMoan"
BlanesMoanRKN = _named("blanes_moan_rkn", "Blanes-Moan optimised fourth-order RKN splitting.")
BlanesMoanRKN.__name__ = BlanesMoanRKN.__qualname__ = "BlanesMoanRKN"

__all__ = [
    "DRIFT",
    "KICK",
    "METHODS",
    "PEFRL",
    "BlanesMoan",
    "BlanesMoanRKN",
    "Splitting",
    "Yoshida4",
    "Yoshida6",
    "alternate",
    "compose",
]
