"""Neighbour lists and their kernels: :mod:`md.neighbors.lists` (:class:`NeighborList`,
:class:`SlotFrame`, :class:`ClusterFrame`, the displacement checks) and the private kernel
modules it calls (``_cell_kernels``, ``_candidates``, ``_build_kernels``,
``_small_box_kernels``, ``_cluster_grid``, ``_cluster_search``, ``_cluster_prune``: the
cluster-pair list's grid, search and prune, ``_exclusion_kernels``, ``_owned_kernels``:
a decomposed rank's search over its owned atoms' rows). The public names are importable from
``md.neighbors``."""

from md.neighbors.lists import (
    ClusterFrame,
    NeighborList,
    SlotFrame,
    largest_displacement2,
    max_displacement2,
)

__all__ = [
    "ClusterFrame",
    "NeighborList",
    "SlotFrame",
    "largest_displacement2",
    "max_displacement2",
]
