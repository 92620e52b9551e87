"""All box geometry in one place: minimum image and wrapping.

Boxes are orthorhombic, given by their edge lengths and a per-axis
periodicity flag. Kernels receive the box as two arrays computed here,
``periodic_lengths`` and their inverses, which are zero along open axes, so
``d - L * rint(d / L)`` becomes a no-op there without a branch. A general
(3, 3) cell later changes this module and the kernels that import it.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray


def periodic_lengths(box: NDArray[np.float64], pbc: NDArray[np.bool_]):
    """Return ``(lengths, inverse_lengths)``, zero along non-periodic axes."""
    lengths = np.where(pbc, box, 0.0).astype(np.float64)
    inverse = np.zeros(3)
    inverse[pbc] = 1.0 / box[pbc]
    return lengths, inverse


def minimum_image(displacements: NDArray[np.float64], box, pbc) -> NDArray[np.float64]:
    """Return displacement vectors reduced to their minimum image (numpy)."""
    lengths, inverse = periodic_lengths(np.asarray(box, float), np.asarray(pbc, bool))
    d = np.array(displacements, dtype=np.float64)
    return d - lengths * np.rint(d * inverse)


def wrap(positions: NDArray[np.float64], box, pbc):
    """Return ``(wrapped, images)``: positions mapped into [0, L) on periodic axes.

    ``wrapped + images * box`` recovers the input exactly up to round-off;
    open axes are left as they are, with image 0.
    """
    box = np.asarray(box, dtype=np.float64)
    pbc = np.asarray(pbc, dtype=bool)
    images = np.zeros(np.shape(positions), dtype=np.int32)
    images[:, pbc] = np.floor(positions[:, pbc] / box[pbc]).astype(np.int32)
    wrapped = positions - images * box
    # floor() can leave a value equal to L after the subtraction by round-off.
    over = wrapped[:, pbc] >= box[pbc]
    if over.any():
        sub = wrapped[:, pbc]
        sub[over] -= np.broadcast_to(box[pbc], sub.shape)[over]
        wrapped[:, pbc] = sub
        img = images[:, pbc]
        img[over] += 1
        images[:, pbc] = img
    return wrapped, images


@njit(cache=True, inline="always", error_model="numpy")
def min_image_component(d, length, inverse):
    """Minimum image of one displacement component (length 0: open axis)."""
    return d - length * np.rint(d * inverse)
