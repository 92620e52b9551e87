"""Integrator studies: what ``md integrators`` measures, one module a job.

- :mod:`md.studies.integrator_study`: ``compare_integrators`` (order, stability,
  energy error and cost over a dt ladder) and its CSV files and figures;
- :mod:`md.studies.thermostat_study`: ``compare_thermostats`` (temperature error,
  sampling efficiency, conserved drift);
- :mod:`md.studies.study`: ``prepare_study`` / ``Study.run``, the study of a config
  (what ``md integrators`` does);
- :mod:`md.studies.damping`: numerical damping on a harmonic bond (``md integrators
  --damping``);
- :mod:`md.studies.plot_style`: how the figures tell integrators apart.

The public names of the modules are importable from here (``SOLVER_TOL`` is the
NVE study's; the damping study's is ``md.studies.damping.SOLVER_TOL``).
"""

from md.studies.damping import (
    DAMPING_COLUMNS,
    DAMPING_FILES,
    OMEGA_DT,
    DampingRow,
    DampingStudy,
    bond_oscillator,
    default_integrators,
    measure_damping,
    plot_damping,
    prepare_damping,
    theory_curve,
    write_damping_csv,
)
from md.studies.integrator_study import (
    CSV_COLUMNS,
    MIN_FIT_POINTS,
    MIN_FIT_SLOPE,
    SOLVER_TOL,
    TOLERANCES,
    WORK_PRECISION_COLUMNS,
    IntegratorReport,
    RunRecord,
    compare_integrators,
    fit_order,
    plot_energy_vs_time,
    plot_error_vs_dt,
    plot_work_precision,
    write_csv,
    write_work_precision_csv,
)
from md.studies.plot_style import (
    FAMILIES,
    STYLES,
    grouped,
    legend_outside,
    pyplot,
    reference_slopes,
    styles,
)
from md.studies.study import (
    INTEGRATOR_FILES,
    MAX_DTS,
    MAX_STUDY_STEPS,
    REFERENCES,
    THERMOSTAT_FILES,
    Study,
    StudyResults,
    ThermostatSetup,
    prepare_study,
)
from md.studies.thermostat_study import (
    THERMOSTAT_CSV_COLUMNS,
    ThermostatReport,
    compare_thermostats,
    plot_thermostats,
    statistical_inefficiency,
    write_thermostat_csv,
)

__all__ = [
    "CSV_COLUMNS",
    "DAMPING_COLUMNS",
    "DAMPING_FILES",
    "FAMILIES",
    "INTEGRATOR_FILES",
    "MAX_DTS",
    "MAX_STUDY_STEPS",
    "MIN_FIT_POINTS",
    "MIN_FIT_SLOPE",
    "OMEGA_DT",
    "REFERENCES",
    "SOLVER_TOL",
    "STYLES",
    "THERMOSTAT_CSV_COLUMNS",
    "THERMOSTAT_FILES",
    "TOLERANCES",
    "WORK_PRECISION_COLUMNS",
    "DampingRow",
    "DampingStudy",
    "IntegratorReport",
    "RunRecord",
    "Study",
    "StudyResults",
    "ThermostatReport",
    "ThermostatSetup",
    "bond_oscillator",
    "compare_integrators",
    "compare_thermostats",
    "default_integrators",
    "fit_order",
    "grouped",
    "legend_outside",
    "measure_damping",
    "plot_damping",
    "plot_energy_vs_time",
    "plot_error_vs_dt",
    "plot_thermostats",
    "plot_work_precision",
    "prepare_damping",
    "prepare_study",
    "pyplot",
    "reference_slopes",
    "statistical_inefficiency",
    "styles",
    "theory_curve",
    "write_csv",
    "write_damping_csv",
    "write_thermostat_csv",
    "write_work_precision_csv",
]
