"""Config texts that several test files run, laid out once and varied by arguments.

``config_text`` joins the tables of a run from their bodies; ``fcc_run`` and
``argon_structure_run`` are the two small runs the input tests vary (a potential, an
integrator, a structure file). Each returns TOML text for the test to write;
``to_toml`` writes a config held as a dict (the fuzzed ones). The LJ run most other
tests write is ``conftest.lj_config_text``.

>>> import tomllib
>>> tomllib.loads(fcc_run('type = "lj"\\ncutoff = 2.5'))["system"]["cells"]
4
>>> tomllib.loads(argon_structure_run("s.xyz"))["system"]
{'structure': 's.xyz', 'temperature': 50.0}
"""

from __future__ import annotations

import math
from collections.abc import Sequence

#: The [integrator] body of the fcc runs.
VERLET = 'type = "verlet"\ndt = 0.002'

#: Argon's LJ in metal units (epsilon [eV], sigma and cutoff [Angstrom]).
ARGON_LJ = 'type = "lj"\nepsilon = 0.0104\nsigma = 3.4\ncutoff = 8.5'


def config_text(
    *,
    system: str,
    potentials: str | Sequence[str],
    integrator: str,
    run: str,
    output: str,
    top: str = "",
) -> str:
    """The TOML text of a run: ``top`` (top-level keys), then each table from its body.

    ``potentials`` is one ``[[potentials]]`` body or a sequence of them. Tables are
    separated by a blank line, in the order the manual shows them.
    """
    bodies = [potentials] if isinstance(potentials, str) else list(potentials)
    parts = [top] if top else []
    parts.append("[system]\n" + system)
    parts += ["[[potentials]]\n" + body for body in bodies]
    parts += ["[integrator]\n" + integrator, "[run]\n" + run, "[output]\n" + output]
    return "\n\n".join(parts) + "\n"


def fcc_run(potential: str, integrator: str = VERLET) -> str:
    """256 atoms of fcc (4 cells, density 0.8, T 0.5, lj units), 4 steps, out.h5 every 2.

    ``potential`` is the body of the one ``[[potentials]]`` table, ``integrator`` that
    of ``[integrator]``.
    """
    return config_text(
        top='units = "lj"\nseed = 1',
        system='lattice = "fcc"\ncells = 4\ndensity = 0.8\ntemperature = 0.5',
        potentials=potential,
        integrator=integrator,
        run="steps = 4\nthermo_every = 2",
        output='path = "out.h5"\nevery = 2',
    )


def argon_structure_run(
    name: str,
    *,
    system: str = "temperature = 50.0",
    top: str = "",
    dt: float = 1.0,
    run: str = "steps = 4",
    output: str = 'path = "s.h5"\nevery = 2',
) -> str:
    """Argon read from the structure file ``name`` (metal units, ARGON_LJ, velocity Verlet).

    ``system`` holds the ``[system]`` keys after ``structure``; ``dt`` is in fs;
    ``run`` and ``output`` are those tables' bodies.
    """
    return config_text(
        top=top,
        system=f'structure = "{name}"\n{system}',
        potentials=ARGON_LJ,
        integrator=f'type = "verlet"\ndt = {dt}',
        run=run,
        output=output,
    )


# ------------------------------------------------------------------ a TOML writer
def toml_value(value) -> str:
    """A TOML value: non-finite floats as nan/inf, strings with \\u escapes."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return toml_key(value)
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{toml_key(k)} = {toml_value(v)}" for k, v in value.items()) + "}"
    raise TypeError(value)


def toml_key(key: str) -> str:
    escaped = key.replace("\\", "\\\\").replace('"', '\\"')
    return '"' + "".join(c if c.isprintable() else f"\\u{ord(c):04x}" for c in escaped) + '"'


def _array_of_tables(value) -> bool:
    return isinstance(value, list) and bool(value) and all(isinstance(v, dict) for v in value)


def to_toml(data: dict) -> str:
    """TOML for a config dict: top-level values, then tables and arrays of tables (their
    own nested values inline)."""
    lines = [
        f"{toml_key(k)} = {toml_value(v)}"
        for k, v in data.items()
        if not isinstance(v, dict) and not _array_of_tables(v)
    ]
    for key, value in data.items():
        if isinstance(value, dict):
            lines.append(f"[{toml_key(key)}]")
            lines += [f"{toml_key(k)} = {toml_value(v)}" for k, v in value.items()]
        elif _array_of_tables(value):
            for entry in value:
                lines.append(f"[[{toml_key(key)}]]")
                lines += [f"{toml_key(k)} = {toml_value(v)}" for k, v in entry.items()]
    return "\n".join(lines) + "\n"
