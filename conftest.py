"""pytest's collection of the packages' doctests (``testpaths`` names md, potentials and
integrators; the fixtures live in tests/conftest.py)."""

import collections
import importlib.util

# md.cuda's engine and kernels import numba.cuda, which needs numba-cuda (the test extra
# installs it); without it their doctests are not collected, as md.cuda loads them only
# for a run on the device.
collect_ignore = (
    []
    if importlib.util.find_spec("numba_cuda") is not None
    else ["md/cuda/engine.py", "md/cuda/_kernels.py"]
)


#: The test files that take longest on a cold cache (a subprocess compiling the mixed
#: path in a cache of its own, the CUDA simulator's checks and its PTX build, the first
#: compiles of the cluster and pair kernels), longest first, from a cold run's
#: ``--durations=0`` summed per file: run first, so that under ``--dist loadfile`` each
#: worker starts on one and the rest fill in around them (the longest jobs first). xdist
#: orders files by their number of tests unless told not to (``--no-loadscope-reorder``
#: in pyproject.toml): that put test_reproducible's two tests (~35 s cold) last, where
#: they ran alone while the other worker sat idle.
HEAVY_FIRST = (
    "tests/test_pair_styles.py",
    "tests/test_reproducible.py",
    "tests/test_gpu.py",
    "tests/test_clusters.py",
    "tests/test_potentials.py",
    "tests/test_output_files.py",
    "tests/test_mpi.py",
    "tests/test_neighbors.py",
    "tests/test_plugins.py",
    "tests/test_vs_lammps.py",
    "tests/test_reliability_runs.py",
)


def pytest_collection_modifyitems(session, config, items):
    """The files of :data:`HEAVY_FIRST` first, in its order; the rest after them, those
    with more tests first (xdist's own order), each file's tests as collected."""
    rank = {name: k for k, name in enumerate(HEAVY_FIRST)}
    sizes = collections.Counter(item.nodeid.split("::")[0] for item in items)

    def key(item):
        name = item.nodeid.split("::")[0]
        return (rank.get(name, len(HEAVY_FIRST)), -sizes[name], name)

    items.sort(key=key)  # stable: a file's tests keep their order
