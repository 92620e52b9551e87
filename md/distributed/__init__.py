"""One system over several MPI ranks: spatial domain decomposition (mpi4py).

The cell is cut into one brick per rank (:mod:`md.distributed.grid`). Each rank *owns*
the atoms in its brick and keeps *ghost* copies of the atoms within the reach
of it (the neighbour-list radius, cutoff + skin, or more where bonds are
longer), periodic images included. Ghosts are found as LAMMPS's brick
communication finds them: three sweeps, along a, b and c, each sending to the
two face neighbours the atoms (owned, and ghosts from the earlier sweeps)
within the reach of their faces, shifted by a cell vector across a periodic
boundary; a single brick along an axis sends to itself.

A rank's owned atoms followed by its ghosts form an ordinary system, open
along the cut axes (images explicit) and periodic along the others whose cell
vector has no component along a cut axis (no ghosts there: the cell list
finds those images as a single process does,
:func:`md.distributed.grid.local_periodic_axes`), which the rank evaluates with an ordinary
:class:`md.forcefield.ForceField` (threaded kernels and all). Its neighbour
list keeps only the pairs whose designated atom it owns (the lower id when the
ids' sum is even, the higher when odd: :meth:`md.neighbors.NeighborList.keep_owned`,
which splits the pairs across each face about evenly; the search applies the rule
itself, over the owned atoms' rows only, so a pair of two ghosts is never a candidate
and the pair kernels walk no ghost row), so every pair
is evaluated once in the whole run and pairs of two ghosts not at all; each
bond (angle) is evaluated by the owner of its first atom (vertex), with its
partners' nearest copies. The forces on ghosts then go back to their owners
along the reverse of the sweeps (newton on, in LAMMPS's terms), and the
energy and virial are plain sums over the ranks.

Per force evaluation: the owned positions are written into the local system
(each at its image nearest the brick), ghost positions are sent along the
sweeps (a sweep's two in flight together; packed, sent and unpacked by one
compiled call making the MPI calls itself, ``_mpi_kernels``, else persistent
mpi4py messages), the local forces are computed, the ghosts' forces are sent
back alike, and one reduction sums the energy and virial and tells every rank
whether any failed, whether any list was outrun, and what the next step start
needs. Inside a step of the loop that is the step's only reduction: the calls
that take a held result are decided alike on every rank from what the steps
before showed (``DistributedForceField.step_begins``); outside steps they
agree by a reduction. The list is rebuilt when the largest
move of any atom since the last build exceeds skin/2 (a global maximum; a
cell deformation is allowed for as :class:`md.neighbors.NeighborList` does).
Atoms migrate to the rank whose brick holds them at rebuilds taken between
steps: :class:`DistributedSimulation` rebuilds at the start of a step when
some atom's coming move could take it past the limit (each atom's next move
bounded from its last two, ``moved_since`` in ``_domain_kernels``), and lays the
ghosts and the list out where the step is expected to take the atoms
(dt v + dt^2 a / 2), so that its lists last as many steps as one process's;
a rebuild forced inside a step (by an integrator's stage, or a move the
look-ahead missed) keeps the owners and widens the ghost shell by as far as
owned atoms have left their bricks, and the next step migrates them. A
migration changes only the rows that move (arrivals take the leavers' rows),
so a rank's atom order follows its history (checkpoints record it); its
messages are packed and refilled by one compiled call each. A ghost sweep is
two compiled passes around its messages (the face atoms, their rows and the
swap tables; the arrived rows laid out as ghosts) in memory the Domain keeps
between builds, and the compiled halo's exchanges use those tables as they
are (``md/distributed/_domain_kernels.py``).

Reductions add in rank order on every rank (an all-gather, then a sum), so
all ranks hold the same bits and a run on P ranks is deterministic; runs on
different P agree to round-off (the force sums' order differs). Langevin's
noise is keyed by atom id and step, so it does not depend on P at all.

Nothing here runs, and mpi4py is not imported, unless a launcher started
more than one process (:func:`mpi_ranks`).

The package, one module a job, bottom first:

- :mod:`md.distributed.grid`: the bricks (:class:`Grid`) and the choice of grid;
  their kernels (fractional coordinates, the ghost sweeps and their swap tables,
  migration's pack and refills, the look-ahead) in ``_domain_kernels``;
- :mod:`md.distributed.ranks`: how many ranks a launcher started, the
  communicator (:class:`MPIRanks`), its clock, and :func:`agree`;
- :mod:`md.distributed.migration`: atoms moving to the ranks whose bricks hold them;
- :mod:`md.distributed.halo`: a rank's brick, owned atoms and ghosts (:class:`Domain`);
- :mod:`md.distributed.balance`: when and where the planes between bricks move
  (:class:`~md.distributed.balance.LoadBalance`);
- :mod:`md.distributed.forcefield`: one rank's force field
  (:class:`DistributedForceField`);
- :mod:`md.distributed.views`: the whole system gathered for rank 0's observers;
- :mod:`md.distributed.simulation`: :class:`DistributedSimulation`.

This ``__init__`` re-exports their public names, and imports them inside
:func:`md._kernel_cache.kernel_cache` so numba caches the kernels per user.
"""

from md._kernel_cache import kernel_cache

# Kernel modules are imported here so numba caches them per user (md._kernel_cache).
with kernel_cache():
    from md.distributed.bonded import longest_arm
    from md.distributed.forcefield import (
        BOND_SKINS,
        LOOKAHEAD,
        DistributedForceField,
    )
    from md.distributed.grid import (
        Grid,
        balanced_cuts,
        brick_widths,
        check_grid,
        choose_grid,
        grid_candidates,
        largest_grid,
        local_periodic_axes,
    )
    from md.distributed.halo import Domain
    from md.distributed.migration import RowStore, migrate
    from md.distributed.ranks import (
        SIZE_VARIABLES,
        CommClock,
        MPIRanks,
        agree,
        launch_rank,
        launched_ranks,
        mpi_ranks,
        on_root,
        ranks_per_node,
    )
    from md.distributed.simulation import DistributedSimulation, refuse_undistributable
    from md.distributed.views import Elsewhere, Gathered, GlobalView

__all__ = [
    "BOND_SKINS",
    "LOOKAHEAD",
    "SIZE_VARIABLES",
    "CommClock",
    "DistributedForceField",
    "DistributedSimulation",
    "Domain",
    "Elsewhere",
    "Gathered",
    "GlobalView",
    "Grid",
    "MPIRanks",
    "RowStore",
    "agree",
    "balanced_cuts",
    "brick_widths",
    "check_grid",
    "choose_grid",
    "grid_candidates",
    "largest_grid",
    "launch_rank",
    "launched_ranks",
    "local_periodic_axes",
    "longest_arm",
    "migrate",
    "mpi_ranks",
    "on_root",
    "ranks_per_node",
    "refuse_undistributable",
]
