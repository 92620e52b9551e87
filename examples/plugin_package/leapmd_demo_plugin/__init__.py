"""Example leapmd plug-ins, written from leapmd's public names only.

- :class:`~leapmd_demo_plugin.pairs.Gauss`, a pair style: u(r) = a exp(-(r / width)^2);
- :class:`~leapmd_demo_plugin.bonds.AnharmonicBonds`, a bond style:
  u(r) = k/2 (r - r0)^2 + c (r - r0)^4;
- :class:`~leapmd_demo_plugin.integrators.PositionVerlet`, an integrator: drift, kick, drift.

A config names them by their entry points (``type = "demo_gauss"``, see pyproject.toml)
or by path (``type = "leapmd_demo_plugin.pairs:Gauss"``).
"""
