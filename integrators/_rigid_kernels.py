"""Compiled free-rotor steps of the rotational family (:mod:`integrators.rigid`).

One loop over the bodies each, scalars per body: the splitting into turns about the
principal axes (NO_SQUISH on quaternions, DLM on the rotation matrix), and the
Richardson-iterated and RK4 quaternion updates. Each takes the quaternions (B, 4),
space-frame angular momenta (B, 3), inverse principal moments (B, 3, 0 for a linear
body's axis) and a time span, and writes the new unit quaternions into ``out``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from md.rigid import rotation_entries


@njit(cache=True)
def _normalise_into(out, b, w, x, y, z):
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    out[b, 0], out[b, 1], out[b, 2], out[b, 3] = w / norm, x / norm, y / norm, z / norm


@njit(cache=True)
def _matrix_quaternion_into(out, b, a):
    """Row b of ``out``: the unit quaternion (w >= 0) of the rotation matrix ``a`` (3, 3),
    Shepperd's choice of the largest of the four squared components first."""
    trace = a[0, 0] + a[1, 1] + a[2, 2]
    choice, largest = 0, trace
    for k in range(3):
        if a[k, k] > largest:
            choice, largest = k + 1, a[k, k]
    q = np.empty(4)
    if choice == 0:
        w = 0.5 * math.sqrt(1.0 + trace)
        q[0] = w
        q[1] = (a[2, 1] - a[1, 2]) / (4 * w)
        q[2] = (a[0, 2] - a[2, 0]) / (4 * w)
        q[3] = (a[1, 0] - a[0, 1]) / (4 * w)
    else:
        i, j, n = choice - 1, choice % 3, (choice + 1) % 3
        v = 0.5 * math.sqrt(max(1.0 + 2 * a[i, i] - trace, 0.0))
        q[1 + i] = v
        q[1 + j] = (a[j, i] + a[i, j]) / (4 * v)
        q[1 + n] = (a[n, i] + a[i, n]) / (4 * v)
        q[0] = (a[n, j] - a[j, n]) / (4 * v)
    sign = 1.0 if q[0] >= 0 else -1.0
    _normalise_into(out, b, sign * q[0], sign * q[1], sign * q[2], sign * q[3])


@njit(cache=True)
def _axis_turns(quaternions, angular_momenta, inverse_moments, dt, axes, fractions, on_matrix, out):
    """The free rotor split into turns about the principal axes: turn k about body axis
    ``axes[k]`` over ``fractions[k] * dt``, the body frame turning by +angle and L in it
    by -angle; on the quaternion (a product with the turn's, renormalised at the end) or,
    with ``on_matrix``, on the rotation matrix's columns."""
    a = np.empty((3, 3))
    body = np.empty(3)
    turn = np.zeros(3)
    for b in range(quaternions.shape[0]):
        w, x, y, z = quaternions[b, 0], quaternions[b, 1], quaternions[b, 2], quaternions[b, 3]
        entries = rotation_entries(w, x, y, z)
        for r in range(3):
            for c in range(3):
                a[r, c] = entries[3 * r + c]
        for c in range(3):  # L in the body frame, A^T L
            body[c] = (
                a[0, c] * angular_momenta[b, 0]
                + a[1, c] * angular_momenta[b, 1]
                + a[2, c] * angular_momenta[b, 2]
            )
        for k in range(axes.shape[0]):
            axis = axes[k]
            angle = fractions[k] * dt * body[axis] * inverse_moments[b, axis]
            c, s = math.cos(angle), math.sin(angle)
            i, j = (axis + 1) % 3, (axis + 2) % 3
            li, lj = body[i], body[j]
            body[i] = c * li + s * lj
            body[j] = -s * li + c * lj
            if on_matrix:
                for r in range(3):
                    ai, aj = a[r, i], a[r, j]
                    a[r, i] = c * ai + s * aj
                    a[r, j] = -s * ai + c * aj
            else:  # q (cos(angle/2), sin(angle/2) e_axis)
                half_cos = math.cos(0.5 * angle)
                turn[:] = 0.0
                turn[axis] = math.sin(0.5 * angle)
                t0, t1, t2 = turn[0], turn[1], turn[2]
                w, x, y, z = (
                    w * half_cos - (x * t0 + y * t1 + z * t2),
                    w * t0 + half_cos * x + (y * t2 - z * t1),
                    w * t1 + half_cos * y + (z * t0 - x * t2),
                    w * t2 + half_cos * z + (x * t1 - y * t0),
                )
        if on_matrix:
            _matrix_quaternion_into(out, b, a)
        else:
            _normalise_into(out, b, w, x, y, z)


@njit(cache=True)
def _rate(w, x, y, z, l0, l1, l2, i0, i1, i2):
    """dq/dt = 1/2 (0, omega) q, omega = A I^-1 A^T L, with A(q) as written for any q."""
    a00, a01, a02, a10, a11, a12, a20, a21, a22 = rotation_entries(w, x, y, z)
    u0 = (a00 * l0 + a10 * l1 + a20 * l2) * i0
    u1 = (a01 * l0 + a11 * l1 + a21 * l2) * i1
    u2 = (a02 * l0 + a12 * l1 + a22 * l2) * i2
    o0 = a00 * u0 + a01 * u1 + a02 * u2
    o1 = a10 * u0 + a11 * u1 + a12 * u2
    o2 = a20 * u0 + a21 * u1 + a22 * u2
    return (
        -0.5 * (o0 * x + o1 * y + o2 * z),
        0.5 * (w * o0 + (o1 * z - o2 * y)),
        0.5 * (w * o1 + (o2 * x - o0 * z)),
        0.5 * (w * o2 + (o0 * y - o1 * x)),
    )


@njit(cache=True)
def _unit(w, x, y, z):
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    return w / norm, x / norm, y / norm, z / norm


@njit(cache=True)
def _richardson(quaternions, angular_momenta, inverse_moments, dt, out):
    """2 q(two forward-Euler half steps, each renormalised) - q(one full step), renormalised."""
    for b in range(quaternions.shape[0]):
        w, x, y, z = quaternions[b, 0], quaternions[b, 1], quaternions[b, 2], quaternions[b, 3]
        l0, l1, l2 = angular_momenta[b, 0], angular_momenta[b, 1], angular_momenta[b, 2]
        i0, i1, i2 = inverse_moments[b, 0], inverse_moments[b, 1], inverse_moments[b, 2]
        r = _rate(w, x, y, z, l0, l1, l2, i0, i1, i2)
        full = _unit(w + dt * r[0], x + dt * r[1], y + dt * r[2], z + dt * r[3])
        h = 0.5 * dt
        half = _unit(w + h * r[0], x + h * r[1], y + h * r[2], z + h * r[3])
        r = _rate(half[0], half[1], half[2], half[3], l0, l1, l2, i0, i1, i2)
        half = _unit(half[0] + h * r[0], half[1] + h * r[1], half[2] + h * r[2], half[3] + h * r[3])
        _normalise_into(
            out,
            b,
            2.0 * half[0] - full[0],
            2.0 * half[1] - full[1],
            2.0 * half[2] - full[2],
            2.0 * half[3] - full[3],
        )


@njit(cache=True)
def _rk4(quaternions, angular_momenta, inverse_moments, dt, out):
    """Classical RK4 on dq/dt = 1/2 (0, omega(q)) q at fixed L, renormalised at the end."""
    for b in range(quaternions.shape[0]):
        w, x, y, z = quaternions[b, 0], quaternions[b, 1], quaternions[b, 2], quaternions[b, 3]
        l0, l1, l2 = angular_momenta[b, 0], angular_momenta[b, 1], angular_momenta[b, 2]
        i0, i1, i2 = inverse_moments[b, 0], inverse_moments[b, 1], inverse_moments[b, 2]
        h = 0.5 * dt
        k1 = _rate(w, x, y, z, l0, l1, l2, i0, i1, i2)
        k2 = _rate(
            w + h * k1[0], x + h * k1[1], y + h * k1[2], z + h * k1[3], l0, l1, l2, i0, i1, i2
        )
        k3 = _rate(
            w + h * k2[0], x + h * k2[1], y + h * k2[2], z + h * k2[3], l0, l1, l2, i0, i1, i2
        )
        k4 = _rate(
            w + dt * k3[0], x + dt * k3[1], y + dt * k3[2], z + dt * k3[3], l0, l1, l2, i0, i1, i2
        )
        g = dt / 6.0
        _normalise_into(
            out,
            b,
            w + g * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0]),
            x + g * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1]),
            y + g * (k1[2] + 2 * k2[2] + 2 * k3[2] + k4[2]),
            z + g * (k1[3] + 2 * k2[3] + 2 * k3[3] + k4[3]),
        )
