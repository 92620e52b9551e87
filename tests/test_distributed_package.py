"""md.distributed as a package (one module a job), and the capability probes that its move
replaced by declared protocols: no ``getattr``/``hasattr`` probe comes back in md/,
potentials/ or integrators/ but the listed ones, which read real optional attributes of
foreign objects (or fields by a computed name). No MPI needed."""

from __future__ import annotations

import functools
import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from integrators import VelocityVerlet
from integrators.base import DeclaresAdaptive, DeclaresOrder, Distributable, IntegratorBase
from md.checkpoint import read_checkpoint, write_checkpoint
from md.distributed.simulation import refuse_undistributable
from md.distributed.views import Decomposed, ForceFieldView, ForcesUse, Gathered, WholeSystemUse
from md.observers import Progress, ThermoLog
from md.simulation import VirialUse
from md.state import State

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "md" / "distributed"

#: Every getattr/hasattr left in md/, potentials/ and integrators/: path -> {a piece of
#: the line: why it is no capability probe}. A line holding neither piece fails the test,
#: and so does a piece no longer found (the list would hide a new probe).
ALLOWED = {
    "md/__init__.py": {
        "getattr(importlib.import_module(_LAZY[name]), name)": "the facade's lazy names",
    },
    "md/distributed/views.py": {
        "return getattr(self._integrator, name)": "IntegratorView is a proxy of the integrator",
    },
    "md/config.py": {
        'getattr(obj, "__doc__", None)': "any object's docstring, which may be missing",
    },
    "md/forcefield.py": {
        "getattr(total, field)": "ForceResult fields named by the loop",
        "getattr(result, field)": "ForceResult fields named by the loop",
    },
    "md/rigid.py": {
        "getattr(self, name).copy() for name in self.SAVED": "its own fields, by name",
        "target = getattr(self, name)": "its own fields, by name",
    },
    "md/studies/damping.py": {"getattr(self, name) for name in DAMPING_COLUMNS": "its own fields"},
    "md/studies/integrator_study.py": {
        "getattr(r, work), getattr(r, measure)": "a run record's fields, by name",
    },
    "md/studies/thermostat_study.py": {
        "getattr(self, k) for k in THERMOSTAT_CSV_COLUMNS": "its own fields",
    },
    "md/state.py": {
        'getattr(self, "_ase_momenta", None)': "set by from_ase only (not a field)",
        'getattr(atoms, "_leapmd_velocities", None)': "ASE Atoms made by to_ase only",
    },
    "md/cli/analyze.py": {"getattr(args, name)": "argparse's flag for each analysis"},
    "md/notebook.py": {'hasattr(atoms.universe, "bonds")': "an MDAnalysis Universe's bonds"},
    "md/sweeps/client.py": {'hasattr(os, "sched_getaffinity")': "Linux only"},
    "md/_files.py": {'hasattr(os, "uname")': "not on Windows"},
    "md/plugins.py": {
        "if not hasattr(found, part)": "a plug-in's module:attribute path, followed",
        "found = getattr(found, part)": "a plug-in's module:attribute path, followed",
        'getattr(module, "__file__", None)': "a module's file, absent for built-in modules",
    },
    "potentials/__init__.py": {
        "if not hasattr(found, m)": "a plug-in class's members of the Potential protocol",
        'getattr(found.from_config, "__func__", None)': "whether a plug-in has its own",
    },
    "integrators/__init__.py": {
        "callable(getattr(found, m, None))": "a plug-in integrator's step and describe",
    },
    "potentials/_cluster_ir.py": {
        'getattr(mode, "literal_type", mode)': "numba: a Literal type or a plain one",
        'getattr(arg[10], "literal_value", None)': "numba: only Literal types have it",
    },
    # potentials/_pair_frame.py is changed by another item meanwhile: its probes of the
    # list's clusters and its lazily made scratch buffers are left for it.
    "potentials/_pair_codegen.py": {
        "getattr(kernels, variant_name(entry, flags))": "a generated kernel, by name",
        'getattr(function, "py_func", function)': "a numba dispatcher's Python function",
    },
    "potentials/device_terms.py": {
        'getattr(function, "py_func", function)': "a numba dispatcher's Python function",
        'hasattr(value, "py_func")': "whether a value is a numba dispatcher (any kind)",
    },
    "md/cuda/_kernels.py": {"getattr(math, name) for name in _MATH": "math's functions, by name"},
    "potentials/_codegen.py": {
        'getattr(value, "py_func", value)': "a numba dispatcher's Python function",
    },
    "potentials/_pair_frame.py": {
        'getattr(neighbors, "clusters", None)': "left for the pair frame's own item",
        'getattr(self, "_cluster_scratch", None)': "a buffer made on first use",
        'getattr(self, "_cluster_kept", None)': "kept arrays made on first use",
        'getattr(self, "_scratch", None)': "a buffer made on first use",
        'getattr(self, "_hessian_buffers", None)': "buffers made on first use",
        'getattr(self, "_table_cache", None)': "a cache made on first use",
    },
    "potentials/_bonded_frame.py": {
        'getattr(function, "py_func", function)': "a numba dispatcher's Python function",
        "getattr(term, role)": "the term's energy or curvature function, by role",
        "getattr(term, 'name', term)": "a message naming what was given as a term",
        "getattr(type(self), style)": "the style's own class attribute, by name",
        'getattr(self._loops(), f"{self.ITEM}_forces")': "a generated kernel, by name",
        'getattr(type(self), f"{self.ITEM}_style")': "the style's own class attribute",
    },
    "integrators/mtk.py": {"getattr(self, name)": "its own arrays, by name"},
    "integrators/_thermostat.py": {"getattr(self, name)": "its own saved attributes, by name"},
}
PROBE = re.compile(r"\b(getattr|hasattr)\(")


def _probe_lines():
    for package in ("md", "potentials", "integrators"):
        for path in sorted((ROOT / package).rglob("*.py")):
            for number, line in enumerate(path.read_text().splitlines(), 1):
                if PROBE.search(line):
                    yield path.relative_to(ROOT).as_posix(), number, line


def test_no_capability_probes_but_the_listed_optional_attributes():
    found = list(_probe_lines())
    problems = [
        f"{path}:{number}: {line.strip()}"
        for path, number, line in found
        if not any(piece in line for piece in ALLOWED.get(path, {}))
    ]
    assert not problems, "capability probes (use a declared protocol or flag):\n" + "\n".join(
        problems
    )
    stale = [
        (path, piece)
        for path, pieces in ALLOWED.items()
        for piece in pieces
        if not any(p == path and piece in line for p, _, line in found)
    ]
    assert not stale, f"listed but gone (remove them from ALLOWED): {stale}"


def test_the_checker_flags_a_probe():
    """The pattern finds what the list must not let through."""
    line = '        adaptive = bool(getattr(factory, "adaptive", False))'
    assert PROBE.search(line)
    assert not any(piece in line for pieces in ALLOWED.values() for piece in pieces)


def test_the_package_has_one_module_a_job_each_under_800_lines():
    modules = {path.stem: len(path.read_text().splitlines()) for path in PACKAGE.glob("*.py")}
    assert set(modules) == {
        "__init__",
        "_domain_kernels",
        "_mpi_kernels",
        "_verlet_kernels",
        "grid",
        "ranks",
        "migration",
        "halo",
        "bonded",
        "balance",
        "forcefield",
        "views",
        "simulation",
    }
    assert max(modules.values()) < 800, modules
    assert not (ROOT / "md" / "distributed.py").exists()
    assert not (ROOT / "md" / "domain.py").exists()


def test_the_public_names_import_from_the_package_without_mpi():
    code = (
        "import sys\n"
        "from md.distributed import (launch_rank, mpi_ranks, agree, on_root, ranks_per_node,\n"
        "    CommClock, MPIRanks, Domain, DistributedForceField, DistributedSimulation,\n"
        "    Elsewhere, GlobalView, Grid, choose_grid, check_grid, balanced_cuts,\n"
        "    local_periodic_axes, refuse_undistributable)\n"
        "import md.distributed.halo, md.distributed.migration\n"
        "assert md.distributed.Domain is md.distributed.halo.Domain\n"
        "assert 'mpi4py' not in sys.modules\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


class _Plain:
    """An integrator of the Integrator protocol that does not derive from IntegratorBase."""

    dt = 0.005

    def describe(self) -> dict:
        return {"type": "plain"}


def test_an_integrator_runs_decomposed_only_when_it_declares_it():
    assert isinstance(VelocityVerlet(0.005), Distributable)
    refuse_undistributable(VelocityVerlet(0.005), [])
    with pytest.raises(ValueError, match="does not run decomposed"):
        refuse_undistributable(_Plain(), [])  # no flags: not distributed
    flagged = _Plain()
    flagged.distributed, flagged.per_atom_state = True, ()
    assert isinstance(flagged, Distributable)
    refuse_undistributable(flagged, [])
    half = _Plain()
    half.distributed = False
    half.per_atom_state = ()
    with pytest.raises(ValueError, match="does not run decomposed"):
        refuse_undistributable(half, [])


def test_order_and_adaptive_flags_are_declared_by_classes_and_partials_not_functions():
    assert isinstance(VelocityVerlet, DeclaresOrder) and VelocityVerlet.order == 2
    assert isinstance(IntegratorBase, DeclaresAdaptive) and not IntegratorBase.adaptive
    partial = functools.partial(VelocityVerlet)
    assert not isinstance(partial, DeclaresOrder)
    partial.order = 2
    assert isinstance(partial, DeclaresOrder)
    assert not isinstance(lambda dt: VelocityVerlet(dt), DeclaresOrder | DeclaresAdaptive)


class _Ranks:
    """One rank whose reductions are identities."""

    rank, n_ranks = 0, 1

    def max(self, values):
        return values

    def all_objects(self, value):
        return [value]


class _Sim:
    """What Gathered asks of a DistributedSimulation: the views, recorded."""

    def __init__(self) -> None:
        self.ranks, self.asked = _Ranks(), []

    def global_view(self, forces=False, thermo=True):
        self.asked.append(("global", forces, thermo))
        return "view"

    def light_view(self, thermo=True):
        self.asked.append(("light", thermo))
        return "view"


def test_gathered_asks_for_what_the_observer_declares():
    seen = []

    def plain(view):
        seen.append(view)

    class Writer:
        store_forces = True
        uses_virial = False

        def __call__(self, view):
            seen.append(view)

    progress = Progress(SimpleNamespace(update=lambda n: None))
    assert isinstance(progress, VirialUse | WholeSystemUse)
    assert not isinstance(ThermoLog(), VirialUse | WholeSystemUse | ForcesUse)
    sim = _Sim()
    Gathered(plain)(sim)  # declares nothing: the whole system, no forces, the thermo row
    Gathered(Writer())(sim)
    gathered = Gathered(progress)
    gathered.observer = lambda view: seen.append(view)  # (no bar to advance)
    gathered(sim)
    assert sim.asked == [("global", False, True), ("global", True, False), ("light", False)]
    assert seen == ["view"] * 3


def test_a_decomposed_runs_checkpoint_records_its_precision(tmp_path):
    """Rank 0 writes the checkpoint through its view of the force field: the view carries
    the run's precision (it was written as "double" for a mixed run, and then a mixed
    resume on one process was refused)."""
    state = State(
        positions=np.zeros((2, 3)) + [[0.0, 0, 0], [1.0, 0, 0]],
        velocities=np.zeros((2, 3)),
        masses=np.ones(2),
        box=np.full(3, 5.0),
        pbc=np.ones(3, dtype=bool),
    )
    local = SimpleNamespace(precision="mixed", reference_cell=None, n_builds=1)
    layout = {"grid": [2, 1, 1], "owners": np.array([0, 1]), "slots": np.array([0, 0])}
    view = ForceFieldView(local, None, None, np.full((2, 3), np.nan), layout)
    assert isinstance(view, Decomposed)
    path = write_checkpoint(tmp_path / "c.ckpt", state, VelocityVerlet(0.005), view)
    saved = read_checkpoint(path)
    assert saved.precision == "mixed"
    assert saved.decomposition["grid"] == [2, 1, 1]
    assert list(np.asarray(saved.decomposition["owners"])) == [0, 1]


def test_the_force_field_and_the_distributed_one_meet_one_declared_protocol():
    """``potentials.base.ForceSource``: what integrators ask of a force field, met by the
    one-process ForceField (an instance) and the decomposed run's (its class's methods and
    the attributes its constructor sets), so no caller looks for ``compute`` by duck type."""
    import inspect

    import md
    from md.distributed import DistributedForceField
    from potentials import LennardJones
    from potentials.base import ForceSource

    assert isinstance(md.ForceField([LennardJones(cutoff=2.5)]), ForceSource)
    members = ("compute", "compute_subset", "hessian_operator", "invalidate")
    assert all(callable(getattr(DistributedForceField, name)) for name in members)
    source = inspect.getsource(DistributedForceField.__init__)
    for name in ("potentials", "precision", "virial_wanted", "timings"):
        assert f"self.{name} =" in source, name
