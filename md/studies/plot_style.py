"""How the integrator figures tell their curves apart: families, colours, markers, slopes.

Every integrator has its own colour and marker; integrators of one family
share a hue and a line style, and legends list them family by family, outside
the axes, so that no legend covers data. Reference slopes are dashed grey
lines labelled with their order.
"""

from __future__ import annotations

import itertools
import math

#: Families in legend order, each (name, line style).
FAMILIES = (
    ("Verlet family", "-"),
    ("splittings", "--"),
    ("Runge-Kutta", "-."),
    ("implicit", ":"),
    ("other", "-"),
)
#: Registry name -> (family, colour, marker). Aliases share their method's style.
STYLES = {
    "verlet": ("Verlet family", "#1f4e9c", "o"),
    "velocity_verlet": ("Verlet family", "#1f4e9c", "o"),
    "leapfrog": ("Verlet family", "#6f9fdc", "s"),
    "stormer_verlet": ("Verlet family", "#0b2a5e", "^"),
    "symplectic_euler": ("Verlet family", "#9ec3ef", "v"),
    "yoshida4": ("splittings", "#1b7a3a", "D"),
    "forest_ruth": ("splittings", "#1b7a3a", "D"),
    "yoshida6": ("splittings", "#58b947", "P"),
    "pefrl": ("splittings", "#0d4d22", "X"),
    "blanes_moan": ("splittings", "#9ad68a", "h"),
    "blanes_moan_rkn": ("splittings", "#4c8c2f", "p"),
    "respa": ("splittings", "#2e8b8b", "*"),
    "explicit_euler": ("Runge-Kutta", "#e6550d", "<"),
    "rk4": ("Runge-Kutta", "#9c3202", ">"),
    "rkf45": ("Runge-Kutta", "#f7a35c", "d"),
    "implicit_euler": ("implicit", "#b2182b", "o"),
    "implicit_midpoint": ("implicit", "#6a1b7a", "s"),
    "trapezoidal": ("implicit", "#d6338a", "^"),
    "bdf2": ("implicit", "#f16913", "v"),
    "gauss_legendre4": ("implicit", "#3f007d", "D"),
    "xpbd": ("implicit", "#7f3b08", "X"),
}
_SPARE_COLOURS = ("#555555", "#888888", "#222222", "#aaaaaa")
_SPARE_MARKERS = ("o", "s", "^", "v", "D", "P", "X", "h")


def styles(names) -> dict[str, dict]:
    """Return name -> {"family", "color", "marker", "linestyle"} for the given names.

    Names outside :data:`STYLES` form the family "other", each with its own
    grey and marker (distinct among themselves).
    """
    line = dict(FAMILIES)
    spare = itertools.product(_SPARE_MARKERS, _SPARE_COLOURS)
    out = {}
    for name in names:
        if name in STYLES:
            family, colour, marker = STYLES[name]
        else:
            family = "other"
            marker, colour = next(spare)
        out[name] = {"family": family, "color": colour, "marker": marker, "linestyle": line[family]}
    return out


def grouped(names) -> list[str]:
    """``names`` reordered family by family (in :data:`FAMILIES` order), stable within one."""
    order = {family: k for k, (family, _) in enumerate(FAMILIES)}
    style = styles(names)
    return sorted(names, key=lambda n: order[style[n]["family"]])


def legend_outside(fig, ax, handles_labels=None, title: str | None = None) -> None:
    """Put ``ax``'s legend (or the given (handles, labels)) to the right of the axes.

    Save the figure with ``bbox_inches="tight"`` so the legend is kept.
    """
    handles, labels = handles_labels or ax.get_legend_handles_labels()
    if handles:
        ax.legend(
            handles,
            labels,
            loc="upper left",
            bbox_to_anchor=(1.02, 1.0),
            fontsize="x-small",
            title=title,
            title_fontsize="x-small",
            frameon=False,
        )


def reference_slopes(ax, xs, ys, orders, sign: int = 1) -> None:
    """Draw short dashed lines of slope ``sign * p`` for each p in ``orders`` (log-log).

    They sit below the data, in a strip the y axis is extended by: starting
    from the bottom-left corner and rising to the right (sign 1: error
    against dt), or ending in the bottom-right corner (sign -1: error against
    work); each is labelled "order p" at its upper end.
    """
    xs = [x for x in xs if x > 0 and math.isfinite(x)]
    ys = [y for y in ys if y > 0 and math.isfinite(y)]
    orders = sorted({p for p in orders if math.isfinite(p) and p > 0})
    if len(xs) < 2 or not ys or not orders:
        return
    low, high = min(xs), max(xs)
    span = math.log10(high / low) if high > low else 1.0
    run = 10 ** (0.12 * span)  # each line covers an eighth of the x range
    bottom = min(ys) / 10 ** (0.2 + 0.12 * span * max(orders))
    for k, p in enumerate(orders):
        if sign > 0:
            x0 = low * 10 ** (0.15 * span * k)
            x1 = x0 * run
            y0, y1 = bottom, bottom * run**p
            label_at = (x1, y1)
        else:
            x1 = high / 10 ** (0.15 * span * k)
            x0 = x1 / run
            y0, y1 = bottom * run**p, bottom
            label_at = (x0, y0)
        ax.loglog([x0, x1], [y0, y1], color="0.45", ls=(0, (4, 3)), lw=1.0, zorder=0)
        side = "left" if sign > 0 else "right"
        ax.annotate(
            f"order {p:g}",
            label_at,
            fontsize="x-small",
            color="0.3",
            xytext=(2, 2),
            textcoords="offset points",
            ha=side,
        )
    ax.set_ylim(bottom=bottom / 2)


def pyplot():
    """matplotlib's pyplot on the Agg backend (no display), loaded on first use."""
    import matplotlib  # heavy: matplotlib only when plotting

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # heavy: matplotlib only when plotting

    return plt
