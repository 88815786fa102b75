"""The simulated debris: rigid-body dynamics, orbit, geomagnetic field, applied torques, and the
register-level MMC5983MA that the flight software's driver talks to.

The world as it is (scenario keys in `hil.scenario`): the orbit is the circular one or a TLE through
SGP4 (`hil.orbit.TleOrbit`, TEME, the Earth turned by GMST at the scenario's `utc0`); the field is
IGRF-14 to degree 13 by default (`hil.field.IgrfField`, tabulated along the orbit at 1 s and
interpolated, `hil.field.FieldTable`) or the dipole. The magnetometer measures the field through the
host's magnetism, b_meas = S·b_true + h(t) (`hil.host_magnetics`), plus whatever a subclass adds
(`extra_field_body_T`: the de-orbit kit's magnets in `hil.deorbit_sim`). `Truth.b_body_T` stays the
true field. Times here are true times; the box's clock (`hil.box_clock`, `Simulator.clock`) is applied
where the flight software meets the simulator (`hil.sitl`).

Lockstep: the owner calls :meth:`Simulator.advance_to` with the loop time before each flight-loop tick,
so the emulated chip sees a clock that is exactly the flight software's. Between two states the truth
is interpolated (attitude by normalised linear interpolation, rate and inertial field linearly), which
lets the chip sample the field at its own measurement instant inside a loop period.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from fsw.estimation.rotations import quat_to_dcm

from . import dynamics
from .field import FieldTable, IgrfField, b_eci_from_model_T, make_field
from .mmc5983ma import EmulatedMmc5983ma
from .orbit import CircularOrbit, TleOrbit
from .scenario import Scenario


@dataclass
class Truth:
    """The simulator's truth at one instant (SI, body axes unless named)."""

    t_s: float
    omega_radps: np.ndarray
    q_body_to_eci: np.ndarray
    b_body_T: np.ndarray
    moment_Nm: np.ndarray
    #: the field in inertial axes (kept so that interpolating between snapshots needs no rotation back)
    b_eci_T: np.ndarray | None = field(default=None, repr=False, compare=False)


class Simulator:
    """Debris in orbit with its magnetometer; deterministic for a given scenario and seed."""

    def __init__(self, scenario: Scenario, seed: int = 0, max_step_s: float = 0.02,
                 history: int = 256) -> None:
        self.scenario = scenario
        self.max_step_s = float(max_step_s)
        self.rng = np.random.default_rng(seed)
        q0 = dynamics.quat_from_euler_deg(*scenario.attitude_rpy_deg)
        self.body = dynamics.RigidBody(scenario.inertia_kgm2, q0, scenario.omega0_radps)
        self.orbit = make_orbit(scenario)
        #: the Earth's rotation angle at t = 0: GMST at utc0 with a TLE, 0 with the circular orbit
        self.era0_rad = float(getattr(self.orbit, "era0_rad", 0.0))
        self.field = make_field(scenario.field_model, scenario.epoch_year, scenario.field_degree)
        direct = self._b_eci_direct_T
        self._b_eci = FieldTable(direct) if isinstance(self.field, IgrfField) else direct
        self.host = scenario.host.with_period(self.orbit.period_s)
        self.clock = scenario.clock
        #: the TLE the box is given (the scenario's box_tle, else the truth's), and the UTC of t = 0
        self.box_tle = scenario.box_tle or scenario.tle
        self.utc0 = scenario.utc0
        self.t_s = 0.0
        self._moment = np.zeros(3)
        # recent truth snapshots, one per advance: the chip and the SITL telemetry ask for the truth
        # at measurement instants up to a few loop periods back
        self._history: deque[Truth] = deque([self._snapshot()], maxlen=history)
        self.sensor = EmulatedMmc5983ma(self.measured_field_T, clock=lambda: self.t_s, rng=self.rng,
                                        bridge_offset_T=scenario.bridge_offset_T,
                                        extra_noise_T=scenario.noise_T)

    def _b_eci_direct_T(self, t_s):
        return b_eci_from_model_T(self.field, self.orbit.position_eci_m(t_s), t_s, self.era0_rad)

    def b_eci_T(self, t_s: float | np.ndarray) -> np.ndarray:
        """The true field along the orbit in inertial axes [T] at time(s) `t_s`."""
        return self._b_eci(t_s)

    def _snapshot(self) -> Truth:
        b_eci = self.b_eci_T(self.t_s)
        q = self.body.q.copy()
        return Truth(self.t_s, self.body.omega_radps.copy(), q,
                     quat_to_dcm(q).T @ b_eci, self.scenario.moment_Nm(self.t_s).copy(), b_eci)

    def advance_to(self, t_s: float) -> None:
        """Integrate the dynamics up to `t_s` in steps no longer than `max_step_s`."""
        if t_s < self.t_s - 1e-12:
            raise ValueError(f"time runs forward only: at {self.t_s} s, asked for {t_s} s")
        if t_s - self.t_s <= 1e-12:
            return
        while self.t_s < t_s - 1e-12:
            self._step(min(self.max_step_s, t_s - self.t_s))
        self.t_s = t_s
        self._history.append(self._snapshot())

    def _step(self, h: float) -> None:
        """One integration step of `h` seconds, the scenario's applied moment held over it. Subclasses
        that add torques or devices (hil.deorbit_sim) override this, not advance_to."""
        self.scenario.moment_Nm(self.t_s, out=self._moment)
        self.body.step(h, self._moment)
        self.t_s += h

    def truth(self, t_s: float | None = None) -> Truth:
        """Truth at `t_s` (default: now), interpolated between the recent snapshots.

        Raises ValueError for a time older than the kept history rather than answer wrongly.
        """
        hist = self._history
        b = hist[-1]
        if t_s is None or t_s >= b.t_s:
            return b
        if t_s < hist[0].t_s - 1e-12:
            raise ValueError(f"truth at {t_s} s is older than the simulator's history ({hist[0].t_s} s)")
        i = len(hist) - 1
        while hist[i - 1].t_s > t_s:
            i -= 1
        a, b = hist[i - 1], hist[i]
        f = (t_s - a.t_s) / (b.t_s - a.t_s)
        qb = b.q_body_to_eci if np.dot(a.q_body_to_eci, b.q_body_to_eci) >= 0 else -b.q_body_to_eci
        q = (1 - f) * a.q_body_to_eci + f * qb
        q /= np.linalg.norm(q)
        # interpolate the inertial field (smooth along the orbit), then rotate into the body
        b_eci = (1 - f) * _b_eci(a) + f * _b_eci(b)
        b_body = quat_to_dcm(q).T @ b_eci
        return Truth(t_s, (1 - f) * a.omega_radps + f * b.omega_radps, q, b_body,
                     a.moment_Nm if f < 1 else b.moment_Nm, b_eci)

    def field_body_T(self, t_s: float) -> np.ndarray:
        """The true field in body (= sensor) axes at `t_s`."""
        return self.truth(t_s).b_body_T

    def extra_field_body_T(self, t_s: float) -> np.ndarray | None:
        """Fields at the sensor besides the Earth's seen through the host (none here; the kit's magnets
        in `hil.deorbit_sim`)."""
        return None

    def measured_field_T(self, t_s: float) -> np.ndarray:
        """What the emulated chip measures at `t_s`: S·b_true + h(t) + the extra fields, body axes [T]."""
        b = self.field_body_T(t_s)
        if not self.host.is_none:
            b = self.host.measured_T(b, t_s)
        extra = self.extra_field_body_T(t_s)
        return b if extra is None else b + extra


def make_orbit(scenario: Scenario):
    """The truth's orbit: the scenario's TLE through SGP4 when it has one, else its circular orbit."""
    if scenario.tle is not None:
        return TleOrbit(*scenario.tle, scenario.utc0)
    return CircularOrbit(scenario.altitude_m, scenario.inclination_deg, scenario.raan_deg, scenario.arg_lat0_deg)


def _b_eci(tr: Truth) -> np.ndarray:
    """A snapshot's field in inertial axes (rotated back from the body when the snapshot did not keep it)."""
    return tr.b_eci_T if tr.b_eci_T is not None else quat_to_dcm(tr.q_body_to_eci) @ tr.b_body_T
