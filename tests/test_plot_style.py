"""The study figures tell their curves apart: one colour and marker per integrator."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from integrators import INTEGRATORS  # noqa: E402
from md.studies.plot_style import FAMILIES, grouped, legend_outside, reference_slopes, styles  # noqa: E402


def test_every_integrator_has_its_own_colour_and_marker():
    """Over the registry, each class (aliases share their method's style) gets a distinct
    (colour, marker) pair, and a family shares its line style."""
    one_name = {}
    for name, cls in INTEGRATORS.items():
        one_name.setdefault(cls, name)
    names = list(one_name.values()) + ["someone_elses", "another_one"]
    style = styles(names)
    pairs = [(style[n]["color"], style[n]["marker"]) for n in names]
    assert len(set(pairs)) == len(pairs)
    families = dict(FAMILIES)
    for n in names:
        assert style[n]["linestyle"] == families[style[n]["family"]]
    assert style["bdf2"]["family"] == style["xpbd"]["family"] == "implicit"
    assert style["someone_elses"]["family"] == "other"
    # The pairs that shared a colour in a 10-colour cycle are told apart.
    for a, b in (
        ("verlet", "rk4"),
        ("leapfrog", "rkf45"),
        ("explicit_euler", "implicit_euler"),
        ("symplectic_euler", "implicit_midpoint"),
    ):
        assert style[a]["color"] != style[b]["color"]


def test_grouped_lists_family_by_family():
    order = grouped(["bdf2", "verlet", "rk4", "pefrl", "implicit_euler", "leapfrog", "mine"])
    assert order == ["verlet", "leapfrog", "pefrl", "rk4", "bdf2", "implicit_euler", "mine"]


def test_legend_beside_the_axes_and_slopes_below_the_data(tmp_path):
    fig, ax = plt.subplots()
    xs = [1e-3, 2e-3, 4e-3, 8e-3]
    for p, name in ((1, "implicit_euler"), (2, "verlet"), (4, "rk4")):
        ax.loglog(xs, [x**p for x in xs], label=name)
    reference_slopes(ax, xs, [x**4 for x in xs], [1, 2, 4])
    legend_outside(fig, ax)
    fig.savefig(tmp_path / "f.png", bbox_inches="tight")
    renderer = fig.canvas.get_renderer()
    legend = ax.get_legend().get_window_extent(renderer)
    axes = ax.get_window_extent(renderer)
    assert legend.x0 >= axes.x1  # no legend over the data
    slopes = [line for line in ax.get_lines() if line.get_color() == "0.45"]
    assert len(slopes) == 3
    lowest = min(x**4 for x in xs)
    for line in slopes:
        assert max(line.get_ydata()) <= lowest  # drawn in the strip below the data
    plt.close(fig)
