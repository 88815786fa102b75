"""SITL side of the identification experiment: the tug is the simulator's torque schedule, the field model
along the orbit is the scenario's.

`SimTug.apply` adds a pulse to the simulator's scenario (`[[torque]]` schedule), `SimTug.stop` cuts the
last one short; the simulator integrates it from its next step, exactly as it does the scenario's own
pulses, and reports it in DEBRIS_SIM_STATE. The flight software gets only callables (it never imports
the simulator).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from fsw.estimation import field_motion as fm
from fsw.estimation.onboard_field import flight_field
from fsw.ident import IdentConfig, IdentExperiment

from .scenario import Scenario, TorquePulse
from .sim import Simulator


class SimTug:
    """A tug whose moment is a pulse in the simulator's torque schedule."""

    def __init__(self, sim: Simulator) -> None:
        self.sim = sim
        self.pulses: list[TorquePulse] = []

    def apply(self, start_s: float, duration_s: float, moment_Nm: np.ndarray) -> None:
        """A pulse commanded at the box's time `start_s`, scheduled at the true time it means."""
        clock = self.sim.clock
        start_s, duration_s = clock.true_s(start_s), duration_s / clock.rate
        p = TorquePulse(float(start_s), float(duration_s), np.array(moment_Nm, float))
        self.pulses.append(p)
        self.sim.scenario = dataclasses.replace(self.sim.scenario, torques=self.sim.scenario.torques + (p,))

    def stop(self, now_s: float) -> None:
        now_s = self.sim.clock.true_s(now_s)
        if not self.pulses:
            return
        last = self.pulses[-1]
        if now_s < last.start_s + last.duration_s:
            cut = TorquePulse(last.start_s, max(now_s - last.start_s, 1e-9), last.moment_Nm)
            torques = tuple(cut if q is last else q for q in self.sim.scenario.torques)
            self.sim.scenario = dataclasses.replace(self.sim.scenario, torques=torques)
            self.pulses[-1] = cut


def field_model(scn: Scenario) -> fm.OrbitField:
    """B_I(t) along the scenario's circular orbit as the box computes it (IGRF-14 at the flight degree;
    hil.sitl.onboard_field); the simulator's truth is the scenario's field model (IGRF degree 13 by
    default) and orbit (a TLE when given)."""
    orbit = fm.CircularOrbitModel(scn.altitude_m, scn.inclination_deg, scn.raan_deg, scn.arg_lat0_deg)
    return flight_field(orbit, scn.epoch_year)


def build_ident(scn: Scenario, sim: Simulator, sigma_b_T: float, inertia_guess_kgm2: float = 100.0,
                b_inertial=None, **config) -> IdentExperiment:
    """The experiment for a SITL run: tug = the simulator's torque schedule; field = `b_inertial`, what
    the box knows (`hil.sitl` hands it the onboard model), else the dipole along the scenario's circular
    orbit (:func:`field_model`)."""
    return IdentExperiment(sigma_b_T=sigma_b_T, b_inertial=b_inertial if b_inertial is not None
                           else field_model(scn).b_eci_T, tug=SimTug(sim),
                           config=IdentConfig(inertia_guess_kgm2=inertia_guess_kgm2, **config))
