"""The bonded frame's loops over listed bonds and angles, compiled once per bonded term.

This file is a template: ``potentials._bonded_frame.kernels_for(term)`` executes it
as a module of its own for each bonded term (named after the term and a hash of all
its compiled code depends on, so numba caches each term's loops apart), with these
names set in that module first:

``_params(table, t) -> p``
    The term's parameters of type ``t``: a tuple read from column ``t`` of the
    (P, T) parameter table.
``_bond(r2, p) -> (u, g)``
    A bond's energy and g = u'(r) / r at squared length ``r2`` (a bond term).
``_bond_curvature(r2, p) -> (u, g, h)``
    The same and h = u''(r), for Hessians (None without the term's curvature).
``_angle(c, p) -> (u, du_dc)``
    An angle's energy and its derivative in c = cos theta, at ``c`` in [-1, 1]
    (an angle term).
``_angle_curvature(c, p) -> (u, du_dc, d2u_dc2)``
    The same and the second derivative in c (None without the term's curvature).

The adapters turn the term's own variable (r or r^2, theta or cos theta) into
these; only the loops of the term's kind are compiled, when first called. No
fastmath here: the loops add in list order, bond by bond, so a term's results do
not depend on how its functions are inlined.
"""

import numpy as np
from numba import njit

from md.box import separation
from potentials._kernels import _add_half_pair_virial


@njit(cache=True, error_model="numpy")
def bond_forces(
    positions, lengths, inverse, tilt, bonds, bond_types, table, forces, virial, energies, virials
):
    """Add bond forces to ``forces`` (zeroed by caller); return (energy, bad).

    bonds: (B, 2) atom indices, bond_types: (B,) columns of ``table``. Writes
    ``virial`` as (xx, yy, zz, yz, xz, xy) of sum r_ij (x) F_ij, and, when
    ``energies`` has length N, half of each bond energy and, into ``virials``
    (N, 6, zeroed), half of its virial to each of its atoms. ``bad`` is -1 when the
    energy is finite, else the first bond whose energy is not (a FENE bond at or
    beyond r_max): the results are then not to be used.
    """
    n = positions.shape[0]
    per_atom = energies.shape[0] == n
    energy = 0.0
    bad = -1
    wxx = wyy = wzz = wyz = wxz = wxy = 0.0
    for b in range(bonds.shape[0]):
        i = bonds[b, 0]
        j = bonds[b, 1]
        dx, dy, dz = separation(positions, i, j, lengths, inverse, tilt)
        u, g = _bond(dx * dx + dy * dy + dz * dz, _params(table, bond_types[b]))  # noqa: F821
        energy += u
        # Force on i is -u'(r) r_ij / r.
        fx = -g * dx
        fy = -g * dy
        fz = -g * dz
        forces[i, 0] += fx
        forces[i, 1] += fy
        forces[i, 2] += fz
        forces[j, 0] -= fx
        forces[j, 1] -= fy
        forces[j, 2] -= fz
        wxx += fx * dx
        wyy += fy * dy
        wzz += fz * dz
        wyz += fz * dy
        wxz += fz * dx
        wxy += fy * dx
        if per_atom:
            energies[i] += 0.5 * u
            energies[j] += 0.5 * u
            _add_half_pair_virial(virials, i, j, fx, fy, fz, dx, dy, dz)
    _store_virial(virial, wxx, wyy, wzz, wyz, wxz, wxy)
    if not np.isfinite(energy):  # some bond's energy is not finite: find the first
        bad = _first_non_finite(positions, lengths, inverse, tilt, bonds, bond_types, table)
    return energy, bad


@njit(cache=True, error_model="numpy")
def _first_non_finite(positions, lengths, inverse, tilt, bonds, bond_types, table):
    """The first bond whose energy is not finite, or -1 (a finite sum overflowed).

    A sum of bond energies is finite only if each is, so the force loop tests its sum
    once and looks for the bond here, rather than testing every bond as it goes."""
    for b in range(bonds.shape[0]):
        dx, dy, dz = separation(positions, bonds[b, 0], bonds[b, 1], lengths, inverse, tilt)
        u, _ = _bond(dx * dx + dy * dy + dz * dz, _params(table, bond_types[b]))  # noqa: F821
        if not np.isfinite(u):
            return b
    return -1


@njit(cache=True, error_model="numpy")
def bond_curvatures(
    positions, lengths, inverse, tilt, bonds, bond_types, table, transverse, radial, unit
):
    """Write each bond's Hessian eigenvalues u'/r, u'' and unit vector; return the first bad bond.

    transverse, radial: (B,); unit: (B, 3), along x_i - x_j (minimum image),
    (1, 0, 0) for a zero-length bond, whose radial value is set to u'/r so
    that K = (u'/r) I. Returns -1 when every bond's energy is finite.
    """
    bad = -1
    for b in range(bonds.shape[0]):
        i = bonds[b, 0]
        j = bonds[b, 1]
        dx, dy, dz = separation(positions, i, j, lengths, inverse, tilt)
        r2 = dx * dx + dy * dy + dz * dz
        u, g, h = _bond_curvature(r2, _params(table, bond_types[b]))  # noqa: F821
        if not np.isfinite(u):
            if bad < 0:
                bad = b
            g = h = 0.0
        transverse[b] = g
        if r2 > 0.0:
            inv_r = 1.0 / np.sqrt(r2)
            radial[b] = h
            unit[b, 0] = dx * inv_r
            unit[b, 1] = dy * inv_r
            unit[b, 2] = dz * inv_r
        else:
            radial[b] = g
            unit[b, 0] = 1.0
            unit[b, 1] = 0.0
            unit[b, 2] = 0.0
    return bad


@njit(cache=True, error_model="numpy")
def angle_forces(
    positions, lengths, inverse, tilt, angles, angle_types, table, forces, virial, energies, virials
):
    """Add angle forces to ``forces`` (zeroed by caller); return (energy, bad).

    angles: (A, 3) atom indices (i, j, k), j the vertex; angle_types: (A,)
    columns of ``table``. Writes ``virial`` (6,) as (xx, yy, zz, yz, xz, xy) of
    x_ij (x) F_i + x_kj (x) F_k summed, and, when ``energies`` has length N, a
    third of each angle's energy and, into ``virials`` (N, 6, zeroed), a third of
    its virial to each of its atoms (LAMMPS's split). ``bad`` is the first angle
    with an arm of zero length, whose terms are left out, or -1.
    """
    n = positions.shape[0]
    per_atom = energies.shape[0] == n
    third = 1.0 / 3.0
    energy = 0.0
    bad = -1
    wxx = wyy = wzz = wyz = wxz = wxy = 0.0
    for a in range(angles.shape[0]):
        i = angles[a, 0]
        j = angles[a, 1]
        m = angles[a, 2]
        ax, ay, az = separation(positions, i, j, lengths, inverse, tilt)
        bx, by, bz = separation(positions, m, j, lengths, inverse, tilt)
        ra2 = ax * ax + ay * ay + az * az
        rb2 = bx * bx + by * by + bz * bz
        if not (ra2 > 0.0 and rb2 > 0.0):
            if bad < 0:
                bad = a
            continue
        rab = np.sqrt(ra2) * np.sqrt(rb2)
        c = (ax * bx + ay * by + az * bz) / rab
        c = min(max(c, -1.0), 1.0)
        u, d1 = _angle(c, _params(table, angle_types[a]))  # noqa: F821
        energy += u
        # F_i = -du/dc dc/dx_i, dc/dx_i = b / (|a||b|) - c a / |a|^2 (LAMMPS's a11, a12, a22).
        a11 = d1 * c / ra2
        a12 = -d1 / rab
        a22 = d1 * c / rb2
        fix = a11 * ax + a12 * bx
        fiy = a11 * ay + a12 * by
        fiz = a11 * az + a12 * bz
        fkx = a22 * bx + a12 * ax
        fky = a22 * by + a12 * ay
        fkz = a22 * bz + a12 * az
        forces[i, 0] += fix
        forces[i, 1] += fiy
        forces[i, 2] += fiz
        forces[m, 0] += fkx
        forces[m, 1] += fky
        forces[m, 2] += fkz
        forces[j, 0] -= fix + fkx
        forces[j, 1] -= fiy + fky
        forces[j, 2] -= fiz + fkz
        w0 = ax * fix + bx * fkx
        w1 = ay * fiy + by * fky
        w2 = az * fiz + bz * fkz
        w3 = ay * fiz + by * fkz
        w4 = ax * fiz + bx * fkz
        w5 = ax * fiy + bx * fky
        wxx += w0
        wyy += w1
        wzz += w2
        wyz += w3
        wxz += w4
        wxy += w5
        if per_atom:
            for atom in (i, j, m):
                energies[atom] += third * u
                virials[atom, 0] += third * w0
                virials[atom, 1] += third * w1
                virials[atom, 2] += third * w2
                virials[atom, 3] += third * w3
                virials[atom, 4] += third * w4
                virials[atom, 5] += third * w5
    _store_virial(virial, wxx, wyy, wzz, wyz, wxz, wxy)
    return energy, bad


@njit(cache=True, error_model="numpy")
def angle_hessian_blocks(positions, lengths, inverse, tilt, angles, angle_types, table, blocks):
    """Write each angle's 9x9 Hessian block into ``blocks`` (A, 9, 9); return the first
    angle with an arm of zero length (its block left zero), or -1.

    Rows and columns run over (x_i, x_j, x_k), three axes each. With
    c = cos theta, g its gradient and G its Hessian, the block is
    u''(c) g g^T + u'(c) G. In the arms a = x_i - x_j, b = x_k - x_j (unit
    vectors e_a, e_b, projectors P_a = I - e_a e_a^T, P_b):
    dc/da = (e_b - c e_a) / |a| =: g_a (g_b likewise), d2c/da2 =
    -(e_a g_a^T + g_a e_a^T) / |a| - c P_a / |a|^2, d2c/da db =
    P_b / (|a||b|) - e_a g_b^T / |a|; then x_i moves a, x_k moves b and x_j
    moves both by minus its displacement.
    """
    g = np.empty(9)
    haa = np.empty((3, 3))
    hbb = np.empty((3, 3))
    hab = np.empty((3, 3))
    bad = -1
    for q in range(angles.shape[0]):
        block = blocks[q]
        block[:, :] = 0.0
        i = angles[q, 0]
        j = angles[q, 1]
        m = angles[q, 2]
        ax, ay, az = separation(positions, i, j, lengths, inverse, tilt)
        bx, by, bz = separation(positions, m, j, lengths, inverse, tilt)
        ra = np.sqrt(ax * ax + ay * ay + az * az)
        rb = np.sqrt(bx * bx + by * by + bz * bz)
        if not (ra > 0.0 and rb > 0.0):
            if bad < 0:
                bad = q
            continue
        ea = (ax / ra, ay / ra, az / ra)
        eb = (bx / rb, by / rb, bz / rb)
        c = min(max(ea[0] * eb[0] + ea[1] * eb[1] + ea[2] * eb[2], -1.0), 1.0)
        _, d1, d2 = _angle_curvature(c, _params(table, angle_types[q]))  # noqa: F821
        for x in range(3):
            g[x] = (eb[x] - c * ea[x]) / ra
            g[6 + x] = (ea[x] - c * eb[x]) / rb
            g[3 + x] = -g[x] - g[6 + x]
        for x in range(3):
            for y in range(3):
                delta = 1.0 if x == y else 0.0
                haa[x, y] = -(ea[x] * g[y] + g[x] * ea[y]) / ra - c * (delta - ea[x] * ea[y]) / (
                    ra * ra
                )
                hbb[x, y] = -(eb[x] * g[6 + y] + g[6 + x] * eb[y]) / rb - c * (
                    delta - eb[x] * eb[y]
                ) / (rb * rb)
                hab[x, y] = (delta - eb[x] * eb[y]) / (ra * rb) - ea[x] * g[6 + y] / ra
        for x in range(3):
            for y in range(3):
                # d2c over (x_i, x_j, x_k) from the arm blocks, times u'(c)
                h00 = haa[x, y]
                h02 = hab[x, y]
                h20 = hab[y, x]
                h22 = hbb[x, y]
                block[x, y] = d1 * h00
                block[x, 6 + y] = d1 * h02
                block[6 + x, y] = d1 * h20
                block[6 + x, 6 + y] = d1 * h22
                block[x, 3 + y] = -d1 * (h00 + h02)
                block[3 + x, y] = -d1 * (h00 + h20)
                block[6 + x, 3 + y] = -d1 * (h20 + h22)
                block[3 + x, 6 + y] = -d1 * (h02 + h22)
                block[3 + x, 3 + y] = d1 * (h00 + h02 + h20 + h22)
        if d2 != 0.0:
            for x in range(9):
                for y in range(9):
                    block[x, y] += d2 * g[x] * g[y]
    return bad


@njit(cache=True, inline="always")
def _store_virial(virial, wxx, wyy, wzz, wyz, wxz, wxy):
    """Write the six sums into ``virial`` as (xx, yy, zz, yz, xz, xy)."""
    virial[0] = wxx
    virial[1] = wyy
    virial[2] = wzz
    virial[3] = wyz
    virial[4] = wxz
    virial[5] = wxy
