"""The GPU path: the whole time step on one NVIDIA GPU, compiled by numba-cuda.

``Simulation(..., device="cuda")`` (``[run] device = "cuda"``, ``md run --device cuda``)
runs its steps here. Modules:

``md.cuda`` (this file)
    :data:`DEVICES`, :func:`refusal` (what keeps a run off the device: numba-cuda or a GPU
    missing, or a part of the run not ported, named) and :func:`device_engine`, which
    checks and builds the engine. Light: ``numba.cuda`` is imported only by the two below,
    and only when a run asks for the device.
``md.cuda.engine``
    :class:`~md.cuda.engine.DeviceEngine`: the device state for a run, the step, the
    host copies at output intervals, the sums.
``md.cuda._kernels``
    The kernels: the counting-sort cell list and the full neighbour list, the pair, bond
    and angle force kernels compiled per potential from the frames' own term functions
    (``potentials.device_terms``), the integrator passes, the observables' sums.

What runs on the device: the pair potentials of the pair-kernel frame (every term, every
cutoff mode, double and mixed precision), the bond and angle potentials of the bonded
frame, velocity Verlet, leapfrog, Langevin (BAOAB, the CPU path's noise) and Bussi (its
stream on the host: eight bytes a half step), the thermo sums; the atoms are sorted on the
device for locality, their cells in the order of a Morton curve, invisibly (every result
comes back in the user's order). A step is three to six launches (docs/guide/gpu.md).

Anything else is refused by :func:`refusal` before a run writes anything. With
``NUMBA_ENABLE_CUDASIM=1`` in the environment before ``numba.cuda`` is first imported, the
same code runs on numba's CUDA simulator (slowly: one Python thread per GPU thread).
"""

from __future__ import annotations

import importlib.util
import os

# Submodules, not the packages: ``import integrators`` (or potentials) imports md, which
# imports this module while the package is still loading.
from integrators.barostats import PressureCoupled
from integrators.base import constraints_of
from integrators.bussi import Bussi
from integrators.langevin import Langevin
from integrators.leapfrog import Leapfrog
from integrators.mtk import MartynaTobiasKlein
from integrators.velocity_verlet import VelocityVerlet
from md.errors import DeviceError
from potentials.device_terms import compilable, kind_of

#: The devices a run may ask for.
DEVICES = ("cpu", "cuda")
#: The integrators whose step runs on the device.
DEVICE_INTEGRATORS = (VelocityVerlet, Leapfrog, Langevin, Bussi)
INSTALL = "install it with: python3 -m pip install 'leapmd[cuda]' (numba-cuda[cu12])"

__all__ = [
    "DEVICES",
    "DEVICE_INTEGRATORS",
    "check_device_name",
    "device_engine",
    "gpu_found",
    "numba_cuda_installed",
    "refusal",
    "simulator_requested",
]


def check_device_name(device) -> str:
    """``device`` if it is one of :data:`DEVICES`, else ValueError naming them."""
    if not isinstance(device, str) or device not in DEVICES:
        raise ValueError(f"device must be one of {', '.join(map(repr, DEVICES))}, got {device!r}")
    return device


def simulator_requested() -> bool:
    """Whether ``NUMBA_ENABLE_CUDASIM=1`` is set (numba-cuda then runs kernels in Python)."""
    return os.environ.get("NUMBA_ENABLE_CUDASIM", "0") not in ("", "0")


def numba_cuda_installed() -> bool:
    """Whether the numba-cuda package is importable (without importing it)."""
    return importlib.util.find_spec("numba_cuda") is not None


def gpu_found() -> bool:
    """Whether numba-cuda finds a CUDA driver and a GPU."""
    # numba.cuda reads NUMBA_ENABLE_CUDASIM when first imported: loaded here only
    from numba import cuda

    return bool(cuda.is_available())


def refusal(state, forcefield, integrator, **options) -> str | None:
    """Why this run cannot go on the device, or None.

    Checks, in order: numba-cuda installed; a GPU present (or the simulator asked for);
    the integrator one of :data:`DEVICE_INTEGRATORS` without constraints (a barostat,
    a thermostat, RESPA, the implicit and other methods are refused by name); every
    potential a pair potential of the pair-kernel frame; the options
    (``neighbor_every``, ``neighbor_check``) at the exact defaults. The message names what
    is missing or not ported and what to do.
    """
    if not numba_cuda_installed():
        return f"numba-cuda is not installed; {INSTALL}"
    if not simulator_requested() and not gpu_found():
        return (
            "no usable NVIDIA GPU was found (numba-cuda sees no CUDA driver or device); "
            "run on a machine with an NVIDIA GPU and its driver, or set "
            "NUMBA_ENABLE_CUDASIM=1 to run on numba's CUDA simulator (slow; for tests)"
        )
    constraints = constraints_of(integrator)
    if not isinstance(integrator, DEVICE_INTEGRATORS) or constraints is not None:
        name = type(integrator).__name__
        if constraints is not None:
            what = f"{name} with rigid bonds (RATTLE)"
        elif isinstance(integrator, PressureCoupled | MartynaTobiasKlein):
            what = f"{name} (a barostat)"
        else:
            what = name
        return (
            f"the integrator {what} does not run on the device yet; it runs "
            f"{', '.join(c.__name__ for c in DEVICE_INTEGRATORS)} without constraints, "
            'barostats or RESPA: use one of those, or device = "cpu"'
        )
    for potential in forcefield.potentials:
        if not compilable(potential):
            return (
                f"the potential {type(potential).__name__} does not run on the device yet; "
                "it runs the pair potentials of the pair-kernel frame (lj, morse, mie, "
                "buckingham, yukawa, soft, table, pair-term plug-ins) and the bond and angle "
                "potentials of the bonded frame (spring, fene, angle_harmonic, "
                'angle_cosine, bond and angle terms): use device = "cpu" for this system'
            )
    if forcefield.neighbor_list is None or kind_of(forcefield.potentials[0]) != "pair":
        return (
            "the device path needs a pair potential, listed first in [[potentials]] "
            "(its kernel starts each step's forces)"
        )
    if (options.get("neighbor_every", 1), options.get("neighbor_check", True)) != (1, True):
        return (
            "[run] neighbor_every and neighbor_check: the device looks at its neighbour "
            "list at every step; leave them at 1 and true"
        )
    if state.n_atoms == 0:
        return "the system has no atoms"
    return None


def device_engine(device: str, state, forcefield, integrator, **options):
    """The engine that runs the steps on ``device``: None for ``"cpu"``; for ``"cuda"`` a
    :class:`~md.cuda.engine.DeviceEngine`, or DeviceError with :func:`refusal`'s message."""
    if check_device_name(device) == "cpu":
        return None
    problem = refusal(state, forcefield, integrator, **options)
    if problem is not None:
        raise DeviceError(f'device = "cuda": {problem}')
    # numba.cuda (and the kernels' compilation) only for a run on the device
    from md.cuda.engine import DeviceEngine

    return DeviceEngine(state, forcefield, integrator)
