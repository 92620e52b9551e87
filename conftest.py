"""pytest's collection of the packages' doctests (``testpaths`` names md, potentials and
integrators; the fixtures live in tests/conftest.py)."""

import importlib.util

# md.cuda's engine and kernels import numba.cuda, which needs numba-cuda (the test extra
# installs it); without it their doctests are not collected, as md.cuda loads them only
# for a run on the device.
collect_ignore = (
    []
    if importlib.util.find_spec("numba_cuda") is not None
    else ["md/cuda/engine.py", "md/cuda/_kernels.py"]
)
