"""Systems without a cell along open axes (a free cluster, a slab read without a c vector):
md render, md analyze --all and md convert give them a box that encloses the atoms (issue 33
item 10: ZeroDivisionError, 'Singular matrix', a GSD box of NaN and a dump box of zero size)."""

from __future__ import annotations

import ase.io
import gsd.hoomd
import matplotlib.image
import numpy as np
import pytest
from ase.build import fcc111
from ase.cluster import Icosahedron

import md
from md.box import enclosing_cell, minimum_image
from md.cli import main
from md.structure import read_structure
from md.trajectory import TrajectoryReader

CONFIG = """
units = "metal"
seed = 5
[system]
structure = "{name}.xyz"
temperature = 30.0
[[potentials]]
type = "lj"
epsilon = 0.0104
sigma = 3.4
cutoff = 6.0
[integrator]
type = "verlet"
dt = 2.0
[run]
steps = 40
[output]
path = "{name}.h5"
every = 20
velocities = true
"""


def _structures() -> dict:
    cluster = Icosahedron("Ar", 3)  # 55 atoms, no cell at all
    slab = fcc111("Ar", (4, 4, 3), a=5.26)
    slab.cell[2] = 0.0  # periodic in x and y (a tilted cell), no length along z
    slab.pbc = [True, True, False]
    slab.info.pop("adsorbate_info", None)  # extxyz cannot store it (and says so)
    return {"cluster": cluster, "slab": slab}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("open")
    paths = {}
    for name, atoms in _structures().items():
        ase.io.write(folder / f"{name}.xyz", atoms, format="extxyz")
        (folder / f"{name}.toml").write_text(CONFIG.format(name=name))
        sim, summary = md.run_config(folder / f"{name}.toml", output=folder / f"{name}.h5")
        assert summary.status == "completed"
        paths[name] = folder / f"{name}.h5"
    with TrajectoryReader(paths["cluster"]) as reader:
        assert np.all(reader.frame(-1).box == 0.0)  # what the viewers failed on
    with TrajectoryReader(paths["slab"]) as reader:
        assert reader.frame(-1).box[2] == 0.0 and reader.frame(-1).tilt[0] != 0.0
    return paths


@pytest.fixture(autouse=True)
def in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)


def _last(path):
    with TrajectoryReader(path) as reader:
        frame = reader.frame(-1)
        return frame, reader.pbc


@pytest.mark.parametrize("name", ["cluster", "slab"])
def test_render_and_analyze_all_draw_an_open_system(runs, tmp_path, name):
    assert main(["render", str(runs[name]), "-o", "shot.png", "--size", "200"]) == 0
    image = matplotlib.image.imread(tmp_path / "shot.png")
    assert image.shape[:2] == (200, 200) and image[..., :3].std() > 0.05
    assert main(["analyze", str(runs[name]), "--all", "--out", "ana", "--no-progress"]) == 0
    assert (tmp_path / "ana" / "snapshot.png").stat().st_size > 1000


@pytest.mark.parametrize("name", ["cluster", "slab"])
def test_gsd_box_encloses_an_open_system_and_reads_back(runs, name):
    assert main(["convert", str(runs[name]), "out.gsd"]) == 0
    frame, pbc = _last(runs[name])
    with gsd.hoomd.open("out.gsd") as trajectory:
        snapshot = trajectory[-1]
    box = np.asarray(snapshot.configuration.box, dtype=float)
    assert np.all(np.isfinite(box)) and np.all(box[:3] > 0)
    along = np.asarray(snapshot.particles.position, dtype=float)[:, ~pbc]
    assert np.all(np.abs(along) < 0.5 * box[:3][~pbc])  # inside the origin-centred box
    state, _ = read_structure("out.gsd", units="metal")
    # A GSD box has no origin: a translation along open axes; float32 may change an image.
    shift = minimum_image(state.positions - frame.positions, frame.box, pbc, frame.tilt)
    np.testing.assert_allclose(shift[:, pbc], 0.0, atol=1e-4)
    np.testing.assert_allclose(shift[:, ~pbc] - shift[0, ~pbc], 0.0, atol=1e-4)


def _bounds(lines) -> np.ndarray:
    return np.array([[float(w) for w in line.split()[:2]] for line in lines])


@pytest.mark.parametrize("name", ["cluster", "slab"])
def test_lammps_data_and_dump_boxes_enclose_the_atoms(runs, name):
    frame, pbc = _last(runs[name])
    assert main(["convert", str(runs[name]), "out.data"]) == 0
    text = open("out.data").read().splitlines()
    data = _bounds([line for line in text if line.split()[2:3] in (["xlo"], ["ylo"], ["zlo"])])
    assert main(["convert", str(runs[name]), "out.dump"]) == 0
    text = open("out.dump").read().splitlines()
    start = max(i for i, line in enumerate(text) if line.startswith("ITEM: BOX BOUNDS"))
    dump = _bounds(text[start + 1 : start + 4])
    for bounds in (data, dump):
        assert np.all(np.isfinite(bounds)) and np.all(bounds[:, 1] > bounds[:, 0])
        inside = (frame.positions >= bounds[:, 0]) & (frame.positions < bounds[:, 1])
        assert np.all(inside[:, ~pbc])  # LAMMPS assigns an atom to a box if lo <= x < hi
    state, _ = read_structure("out.data", units="metal")  # positions from lo: shifted back
    np.testing.assert_allclose(state.positions + data[:, 0], frame.positions, atol=1e-9)


def test_enclosing_cell_keeps_a_stored_edge_that_holds_the_atoms():
    positions = np.array([[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]])
    origin, lengths, tilt = enclosing_cell(
        positions, [10.0, 10.0, 10.0], [True, False, False], [1.0, 2.0, 0.0]
    )
    assert origin.tolist() == [0.0, 0.0, 0.0] and lengths.tolist() == [10.0, 10.0, 10.0]
    assert tilt.tolist() == [0.0, 0.0, 0.0]  # tilts with an open axis are dropped
    origin, lengths, _ = enclosing_cell(positions, [10.0, 0.0, 4.0], [True, False, False])
    assert origin.tolist() == [0.0, 0.5, 0.0]  # the atoms' extent, half a unit beyond
    assert lengths.tolist() == [10.0, 4.0, 5.5]  # z: the stored edge, widened past 5.0
    origin, lengths, _ = enclosing_cell(positions[:1], [0.0, 0.0, 0.0], [False] * 3)
    np.testing.assert_array_equal(lengths, 1.0)  # one atom: a unit box around it


def test_a_tilted_slab_without_a_c_vector_is_checked_against_its_widths():
    """Its perpendicular widths were NaN (0 / 0), so a cell narrower than the minimum image
    needs passed the check and the energy came out wrong (-2.8907 eV, ASE's -2.9223 eV)."""
    from ase.calculators.lj import LennardJones as AseLennardJones

    from potentials import LennardJones

    slab = _structures()["slab"]
    slab.rattle(0.05, seed=1)
    lj = LennardJones(epsilon=0.0104, sigma=3.4, cutoff=8.5)
    with pytest.raises(ValueError, match="its width across x is 12.88"):
        md.ForceField([lj], skin=0.3).compute(md.State.from_ase(slab))
    wide = slab.repeat((2, 2, 1))  # widths 25.8 > 2 (cutoff + skin)
    wide.calc = AseLennardJones(epsilon=0.0104, sigma=3.4, rc=8.5, smooth=False)
    ours = md.ForceField([lj], skin=0.3).compute(md.State.from_ase(wide)).energy
    assert ours == pytest.approx(wide.get_potential_energy(), rel=1e-10)
