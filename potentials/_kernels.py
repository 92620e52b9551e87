"""numba helpers shared by the pair and bond kernels."""

from __future__ import annotations

from numba import njit


@njit(cache=True, inline="always")
def _add_half_pair_virial(virials, i, j, fx, fy, fz, dx, dy, dz):
    """Add half of the pair virial d (x) f to atoms i and j of ``virials`` (N, 6).

    d = x_i - x_j and f the force on i; order (xx, yy, zz, yz, xz, xy), the
    order of the total virial.
    """
    w0 = 0.5 * fx * dx
    w1 = 0.5 * fy * dy
    w2 = 0.5 * fz * dz
    w3 = 0.5 * fz * dy
    w4 = 0.5 * fz * dx
    w5 = 0.5 * fy * dx
    virials[i, 0] += w0
    virials[i, 1] += w1
    virials[i, 2] += w2
    virials[i, 3] += w3
    virials[i, 4] += w4
    virials[i, 5] += w5
    virials[j, 0] += w0
    virials[j, 1] += w1
    virials[j, 2] += w2
    virials[j, 3] += w3
    virials[j, 4] += w4
    virials[j, 5] += w5
