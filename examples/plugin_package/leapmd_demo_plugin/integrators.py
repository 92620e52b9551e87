"""Position Verlet as a leapmd integrator plug-in (an IntegratorBase subclass)."""

from integrators.base import IntegratorBase, check_dt


class PositionVerlet(IntegratorBase):
    """Position Verlet: drift half a step, kick a whole one, drift half a step."""

    order = 2

    def __init__(self, dt):
        self.dt = check_dt(dt)

    def step(self, state, forcefield):
        half = 0.5 * self.dt
        state.positions += half * state.velocities
        forces = forcefield.compute(state, virial=False).forces
        state.velocities += self.dt * forces / state.masses[:, None]
        state.positions += half * state.velocities
        self.end_step(state)

    def describe(self):
        return {"type": "demo_position_verlet", "dt": self.dt}
