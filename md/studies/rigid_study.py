"""``md integrators`` on a config with ``[rigid]``: the rotational family compared.

:func:`prepare_rigid_study` builds a :class:`RigidStudy` (validating every option,
writing nothing): the config's system made of rigid bodies (:mod:`md.rigid_setup`),
equilibrated by NO_SQUISH at the config's dt, and the rotational methods of
:data:`integrators.rigid.ROTATIONS` (or those named), each as
:class:`integrators.rigid.RigidNVE` with velocity Verlet for the centres. They are
measured as the other integrators are (:func:`md.studies.integrator_study.compare_integrators`:
order from the constituent positions, which carry centres and orientations, against
a NO_SQUISH reference at a fine step; stability limit; energy drift; cost), and
written to the same CSV files and figures; there are no thermostats to compare.
In a force field every method is second order (the kicks of force and torque
around the rotation are); on a free body RK4's rotation is fourth order.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from integrators.rigid import ROTATIONS, RigidNVE
from md._files import unwritable_folder
from md.assemble import build_potentials
from md.config import Config, build_system, load_config
from md.errors import ConfigError, SimulationError
from md.rigid import RigidBodies
from md.rigid_setup import body_ids
from md.simulation import Simulation
from md.studies.integrator_study import compare_integrators
from md.studies.study import (
    INTEGRATOR_FILES,
    MAX_STUDY_STEPS,
    Study,
    StudyResults,
    count_option,
    parse_dts,
    positive_option,
)

#: The rotational method of the reference runs.
REFERENCE = "no_squish"


class _Rotation:
    """Makes ``RigidNVE(dt, bodies, rotation)`` over fresh bodies of the study's start."""

    adaptive = False
    order = 2  # in a force field: the kicks around the rotation are second order

    def __init__(self, study: RigidStudy, rotation: str) -> None:
        self.study, self.rotation = study, rotation

    def __call__(self, dt: float) -> RigidNVE:
        state = self.study.state.copy()
        bodies = RigidBodies.from_molecules(state, self.study.ids)
        return RigidNVE(dt, bodies, self.rotation, self.study.config.rigid.exclude)


@dataclass
class RigidStudy(Study):
    """A :class:`~md.studies.study.Study` of the rotational methods (``names``) on rigid
    bodies; ``ids`` are the atoms' molecule ids."""

    ids: object = None

    @property
    def reference(self) -> str:
        return REFERENCE

    def potentials(self) -> list:
        """Fresh potentials (the rotational methods leave the pairs inside bodies out of
        the neighbour list as ``md run`` does: ``[rigid] exclude``)."""
        return build_potentials(self.config, self.state.type_names, self.bonds)

    def run(self, progress: Callable[[str], None] | None = None) -> StudyResults:
        """Measure the rotational methods; write the files; return the results."""
        reports = compare_integrators(
            make_state=self.state.copy,
            potentials_factory=self.potentials,
            integrators={name: _Rotation(self, name) for name in self.names},
            dts=self.dts,
            span=self.span,
            skin=self.config.run.skin,
            units=self.config.units,
            reference=_Rotation(self, REFERENCE),
            reference_order=2,
            measure_dt=self.measure_dt,
            progress=progress,
        )
        self.write(reports, [])
        return StudyResults(reports, [], dict(self.files))


def prepare_rigid_study(
    config: str | os.PathLike | Config,
    integrators: str | Sequence[str] | None = None,
    dts: str | Sequence[float] | None = None,
    span: float | None = None,
    equilibrate: int = 200,
    out: str | os.PathLike | None = None,
    overwrite: bool = False,
    max_steps: int = MAX_STUDY_STEPS,
) -> RigidStudy:
    """Validate and build the study of the rotational methods on a ``[rigid]`` config;
    write nothing. ``integrators`` names rotational methods (default: all of them); the
    other options are :func:`md.studies.study.prepare_study`'s. Raises ConfigError."""
    if not isinstance(config, Config):
        source = Path(config)
        config = load_config(config)
    else:
        source = Path(config.source)
    if config.rigid is None:
        raise ConfigError(f"{config.source}: no [rigid] table: no rigid bodies to study")
    if config.integrator.type not in ("verlet", "velocity_verlet"):
        raise ConfigError(
            f"{config.source}: [integrator] type {config.integrator.type!r}: md integrators "
            "compares the rotational methods at constant energy; use velocity_verlet"
        )
    given = integrators.split(",") if isinstance(integrators, str) else integrators
    names = [n.strip() for n in (given or ROTATIONS) if n.strip()]
    unknown = [n for n in names if n not in ROTATIONS]
    if unknown or not names:
        raise ConfigError(
            f"--integrators: unknown {', '.join(unknown) or '(none given)'} for the rigid "
            f"bodies of [rigid]; the rotational methods are {', '.join(ROTATIONS)}"
        )
    units, dt = config.units, config.integrator.dt
    ladder = [v * units.config_time for v in parse_dts(dts, dt / units.config_time)]
    run_span = 100 * dt if span is None else positive_option(span, "--time") * units.config_time
    equilibrate = count_option(equilibrate, "--equilibrate")
    total = (
        equilibrate
        + 3 * run_span / (min(ladder) / 8)
        + len(names) * sum(run_span / d for d in ladder)
    )
    if total > max_steps:
        raise ConfigError(
            f"the study would take {total:.3g} steps, more than {max_steps:.3g}: choose a "
            "shorter --time or larger time steps (--dt-range)"
        )
    out = Path(out) if out is not None else Path(f"integrators-{source.stem}")
    files = {kind: out / name for kind, name in INTEGRATOR_FILES.items()}
    problem = unwritable_folder(out)
    if problem is not None:
        raise ConfigError(f"output folder {out}: {problem}; choose another --out")
    existing = [str(p) for p in files.values() if p.exists()]
    if existing and not overwrite:
        raise ConfigError(f"output file(s) exist: {', '.join(existing)}; pass --overwrite or --out")
    state, bonds = build_system(config)
    ids = body_ids(config, state, bonds)
    try:
        RigidBodies.from_molecules(state, ids).place(state)
    except ValueError as error:
        raise ConfigError(f"{config.source}: [rigid] bodies: {error}") from None
    study = RigidStudy(
        config,
        state,
        bonds,
        names,
        [],
        ladder,
        run_span,
        ladder[-1] if dts is None else None,
        None,
        out,
        files,
        overwrite,
        ids=ids,
    )
    if equilibrate:
        try:
            bodies = RigidBodies.from_molecules(state, ids)
            integrator = RigidNVE(dt, bodies, REFERENCE, config.rigid.exclude)
            sim = Simulation(state, study.potentials(), integrator, skin=config.run.skin)
            sim.run(equilibrate)
        except (SimulationError, ValueError) as error:
            raise ConfigError(f"{config.source}: equilibration failed: {error}") from None
        state.step, state.time = 0, 0.0
    return study


__all__ = ["RigidStudy", "prepare_rigid_study"]
