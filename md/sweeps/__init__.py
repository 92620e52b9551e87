"""Parameter sweeps and replica ensembles of ``md run``, executed on Dask.

A sweep is the cartesian product of the values of some config keys, times a
number of replicas that differ only in their random seeds. Every run is an
ordinary ``md run`` of its own config (written to ``OUT/configs/``), and
every run writes its own H5MD file ``OUT/<label>.h5``. The runs are tasks on
a Dask ``distributed`` cluster: by default a ``LocalCluster`` with one
single-threaded worker process per core, otherwise any scheduler the user
names (an address, or their own ``Client``; through ``dask-jobqueue`` that is
SLURM, PBS and the like). ``OUT`` must be on a filesystem that the client and
every worker see (a cluster's home or scratch).

Planning (:func:`plan_sweep`)
    Varied keys are dotted paths into the TOML (``system.temperature``,
    ``integrator.dt``, ``potentials.0.cutoff``, ``seed``). Every parameter
    point is written out, read back and validated as ``md run`` would (config,
    system, potentials, integrator, force-field checks) before anything runs;
    the first bad key or value raises :class:`SweepError` naming it.
    Relative ``structure`` and ``bonds_file`` paths are made absolute.

Seeds
    Replica 0 keeps the config's ``seed`` (0 when it has none), so a
    one-replica sweep repeats exactly what ``md run`` of the same config
    does. Replica ``r > 0`` gets ``replica_seed(seed, r)``, drawn from
    ``numpy.random.SeedSequence([seed, r])``. Seeds depend on the replica
    index and the base seed only, not on the other varied values: replica
    ``r`` of every parameter point starts from the same random stream
    (common random numbers, which makes differences between points less
    noisy); adding a value to a sweep leaves the other runs unchanged. An
    explicit ``[integrator] seed`` (a stochastic thermostat's) is varied
    across replicas the same way. Varying ``seed`` itself sets the base seed
    of each point.

Execution (:func:`run_sweep`)
    Each task runs ``python -m md.cli.sweep_child PARENT run CONFIG --threads 1
    --no-progress --quiet`` in a child process. A child process isolates
    crashes and process-wide state (the kernels' thread count, numba), lets
    a multi-threaded Dask worker run several runs at once without sharing a
    GIL, and is exactly ``md run``; it costs about a second of start-up per
    run. The child writes into ``OUT/.partial/<label>/``; only when it exits
    cleanly and its file holds every frame is the file renamed to
    ``OUT/<label>.h5``, so that name always means a complete run. A task holds
    an exclusive lock on ``OUT/.partial/<label>.lock`` (shared with its child)
    so that a retry never writes alongside a run still going. The child dies
    with its worker (Linux ``PR_SET_PDEATHSIG``); Dask then reruns the task
    on another worker (up to the scheduler's ``allowed-failures``), which
    resumes from the run's checkpoint (``md run --resume``: bit-for-bit the
    same result) or starts it afresh. A run that fails (exit 1: the dynamics
    blew up; exit 2: bad input found at run time) is reported with ``md
    run``'s message, its partial files are removed, and the other runs go
    on. Running a sweep again skips runs whose output is complete and was
    written from the same config (an output written from another config is
    refused unless ``overwrite``).

Collation
    Each task also summarises its output (:func:`summarize`): block-averaged
    means and standard errors of temperature, pressure and the energies per
    atom, the total-energy drift per atom (:func:`md.analysis.thermo`), and
    on request the Einstein diffusion coefficient (:func:`md.analysis.msd`),
    after discarding a leading fraction of frames. :class:`SweepTable` holds
    one row per run; it writes ``OUT/sweep.csv`` and plots a result against
    a varied key with replica error bars.

Python API::

    import md
    table = md.sweep("lj.toml", vary={"system.temperature": [0.8, 1.2]}, replicas=4,
                     out="sweep-lj", client=my_dask_client)   # or scheduler="tcp://..."
    table.points("pressure")          # mean and replica standard error per point

``md.sweep`` is :func:`sweep` (a plain function that imports this package on
first use). Importing it does not import Dask; the functions that need Dask import it.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping, Sequence

from md.errors import SweepError
from md.sweeps.client import CONNECT_TIMEOUT, SweepProgress, connect, run_sweep
from md.sweeps.plan import (
    ALIASES,
    CONFIG_DIR,
    LOG_DIR,
    MAX_RUNS,
    PARTIAL_DIR,
    RESULTS,
    TABLE_FILE,
    SweepPlan,
    check_outputs,
    count_runs,
    format_value,
    output_verdict,
    parse_vary,
    plan_sweep,
    replica_seed,
    short_names,
)
from md.sweeps.summary import summarize
from md.sweeps.table import SweepTable, resolve_column

logger = logging.getLogger(__name__)


# --------------------------------------------------------------------- API
def check_options(
    vary: Mapping[str, Sequence] | Sequence = (),
    replicas: int = 1,
    *,
    max_runs: int = MAX_RUNS,
    discard: float = 0.0,
    n_blocks: int = 5,
    workers: int | None = None,
    scheduler: str | None = None,
    diffusion: bool = False,
    plot: str | None = None,
):
    """Check a sweep's options before anything is read, planned or run.

    ``vary`` is as for :func:`plan_sweep` (``"KEY=V1,V2"`` strings are parsed
    here, with at most ``max_runs`` values each); ``plot`` names a result
    column to draw against the first varied key.

    Returns
    -------
    vary : mapping or list of (key, values)
        The varied keys with their values, for :func:`plan_sweep`.
    plot : str or None
        The result column ``plot`` names (aliases resolved).

    Raises
    ------
    SweepError
        Naming the option: a cap below 1 or exceeded, no replicas, a discarded
        fraction outside [0, 1), no blocks or workers, workers with a
        scheduler, a plot column that is unknown, needs ``diffusion``, or has
        no varied key for its x axis.
    """

    def whole(value, option: str) -> int:
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise SweepError(f"{option} must be >= 1, got {value}")
        return value

    whole(max_runs, "--max-runs")
    if isinstance(vary, str):
        vary = [vary]
    if not isinstance(vary, Mapping):
        vary = [
            parse_vary(v, max_values=max_runs) if isinstance(v, str) else tuple(v) for v in vary
        ]
    whole(replicas, "--replicas")
    try:
        in_range = math.isfinite(discard) and 0.0 <= discard < 1.0
    except TypeError:
        in_range = False
    if not in_range:
        raise SweepError(f"--discard must be a fraction in [0, 1), got {discard}")
    whole(n_blocks, "--blocks")
    if workers is not None:
        whole(workers, "--workers")
        if scheduler is not None:
            raise SweepError(
                "--workers sets the size of the local cluster; with --scheduler the cluster's "
                "own workers run the sweep"
            )
    column = None
    if plot is not None:
        column = resolve_column(plot)
        if column == "diffusion" and not diffusion:
            raise SweepError("--plot diffusion needs --diffusion")
        if not vary:
            raise SweepError("--plot needs a --vary key for its x axis")
    n_runs = count_runs(vary, replicas)
    if n_runs > max_runs:
        raise SweepError(
            f"the sweep has {n_runs} runs, more than the cap of {max_runs}; pass "
            f"--max-runs {n_runs} to allow it"
        )
    return vary, column


def sweep(
    config,
    vary: Mapping[str, Sequence] | Sequence[str] = (),
    replicas: int = 1,
    out=None,
    *,
    client=None,
    scheduler: str | None = None,
    workers: int | None = None,
    diffusion: bool = False,
    discard: float = 0.0,
    n_blocks: int = 5,
    overwrite: bool = False,
    progress: Callable[[SweepProgress], None] | None = None,
    max_runs: int = MAX_RUNS,
    timeout: float = CONNECT_TIMEOUT,
) -> SweepTable:
    """Run a sweep of ``md run`` over varied config keys and replicas on Dask.

    Parameters
    ----------
    config : str or Path
        Base TOML config.
    vary : mapping of dotted key to values, or sequence of ``"KEY=V1,V2"``
        E.g. ``{"system.temperature": [0.8, 1.2], "integrator.dt": [0.002, 0.005]}``.
    replicas : int
        Runs per parameter point with different seeds (see the module notes).
    out : str or Path, optional
        Output folder (default ``sweep-<config stem>``), shared by client and workers.
    client : distributed.Client, optional
        Run on this client's cluster (left open).
    scheduler : str, optional
        Address of a Dask scheduler to connect to instead.
    workers : int, optional
        Size of the local cluster made when neither is given (default: cores).
    diffusion : bool
        Also summarise the Einstein diffusion coefficient of every run.
    discard : float
        Leading fraction of each run's frames left out of the averages.
    n_blocks : int
        Blocks of the standard errors of the averages.
    overwrite : bool
        Redo runs whose outputs exist (else complete ones are skipped and
        others refused).
    progress : callable, optional
        Called with a :class:`SweepProgress` as the sweep goes.
    max_runs : int
        Refuse a sweep of more runs than this (default ``MAX_RUNS``, 10000).
    timeout : float
        Seconds to wait for ``scheduler`` to answer (default 30).

    Returns
    -------
    SweepTable
        One row per run; also written to ``OUT/sweep.csv``.
    """
    vary, _ = check_options(
        vary,
        replicas,
        max_runs=max_runs,
        discard=discard,
        n_blocks=n_blocks,
        workers=workers,
        scheduler=scheduler,
        diffusion=diffusion,
    )
    plan = plan_sweep(config, vary, replicas, out, max_runs=max_runs)
    check_outputs(plan, overwrite)
    with connect(client, scheduler, workers, timeout=timeout) as dask_client:
        return run_sweep(
            plan,
            dask_client,
            overwrite=overwrite,
            diffusion=diffusion,
            discard=discard,
            n_blocks=n_blocks,
            progress=progress,
        )


__all__ = [
    "ALIASES",
    "CONNECT_TIMEOUT",
    "CONFIG_DIR",
    "LOG_DIR",
    "MAX_RUNS",
    "PARTIAL_DIR",
    "RESULTS",
    "TABLE_FILE",
    "SweepError",
    "SweepPlan",
    "SweepProgress",
    "SweepTable",
    "check_options",
    "check_outputs",
    "count_runs",
    "connect",
    "format_value",
    "output_verdict",
    "parse_vary",
    "plan_sweep",
    "replica_seed",
    "resolve_column",
    "run_sweep",
    "short_names",
    "summarize",
    "sweep",
]
