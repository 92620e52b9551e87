"""The metal unit constants agree with ASE's, so ASE structures and ours mix."""

import ase.units
import pytest

from md import units


@pytest.mark.parametrize(
    ("ours", "theirs"),
    [
        (units.fs, ase.units.fs),
        (units.ps, 1000.0 * ase.units.fs),
        (units.kB, ase.units.kB),
    ],
    ids=["fs", "ps", "kB"],
)
def test_constants_match_ase(ours, theirs):
    assert ours == pytest.approx(theirs, rel=1e-12, abs=0.0)


def test_metal_unit_system_uses_the_same_constants():
    metal = units.get_units("metal")
    assert metal.kB == pytest.approx(ase.units.kB, rel=1e-12, abs=0.0)
    assert metal.config_time == pytest.approx(ase.units.fs, rel=1e-12, abs=0.0)
    assert units.get_units("lj").kB == 1.0


def test_unknown_unit_system_is_named_in_the_error():
    with pytest.raises(ValueError, match="furlong"):
        units.get_units("furlong")
