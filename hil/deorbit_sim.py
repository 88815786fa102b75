"""The AMDS spacecraft with its de-orbit kit in orbit: the simulator of `hil.sim` plus the torques of
`hil.environment` (aerodynamic, gravity gradient, the kit's magnets) and the kit emulator of
`hil.deorbit_kit`, all advanced in lockstep by :meth:`DeorbitSimulator.advance_to`.

The scenario's optional [deorbit] table (`hil.scenario.DeorbitSpec`) gives the sail, the centre of
pressure, the density model and the initial attitude *w.r.t. the orbital frame* (x_o along the velocity,
z_o to nadir; yaw, pitch, roll in the ZYX sequence), which replaces the scenario's [initial] attitude and
rate: the body starts with `initial_rate_dps` relative to the orbital frame.

Dynamics step: the torques are held over each step (zero-order hold) of at most `max_step_s`; the
magnet pulses last ≥ 80 s and the shutters take 0.5-2 s, so 0.1 s (the 10 Hz loop of the benchmark)
resolves them. The kit emulator is advanced at every step, so the shutters' opening ramps act on the
dynamics as they happen.
"""
from __future__ import annotations

import numpy as np

from fsw.deorbit.controller import AttitudeInput, euler_zyx
from fsw.estimation.rotations import quat_from_dcm, quat_to_dcm

from .deorbit_kit import DeorbitKitEmulator
from .environment import (
    Environment,
    ExponentialAtmosphere,
    dcm_from_euler_zyx,
    orbital_frame_dcm,
    orbital_rate_body_radps,
)
from .kit_field import KitFieldAtSensor
from .scenario import DeorbitSpec, Scenario
from .sim import Simulator, Truth


class DeorbitSimulator(Simulator):
    """`Simulator` with environmental torques and the de-orbit kit; `kit` is its `DigitalLines`."""

    def __init__(self, scenario: Scenario, seed: int = 0, max_step_s: float = 0.1, history: int = 256) -> None:
        super().__init__(scenario, seed=seed, max_step_s=max_step_s, history=history)
        spec = scenario.deorbit or DeorbitSpec()
        self.spec = spec
        self.kit = DeorbitKitEmulator(dipole_Am2=spec.dipole_Am2)
        atmosphere = ExponentialAtmosphere(spec.density_kgm3, spec.density_ref_alt_km * 1e3,
                                           spec.density_scale_height_km * 1e3)
        self.env = Environment(self.orbit, self.field, self.body.J_kgm2, dipole_body_Am2=self.kit.dipole_body_Am2,
                               sail_area_m2=spec.sail_area_m2, body_area_m2=spec.body_area_m2,
                               cd=spec.drag_coefficient, r_cp_body_m=np.array(spec.cp_offset_m),
                               atmosphere=atmosphere, era0_rad=self.era0_rad, b_eci_T=self.b_eci_T)
        self.kit_field = KitFieldAtSensor(self.kit, (spec.pitch_magnet_position_m, spec.yaw_magnet_position_m),
                                          spec.capsule_leakage)
        self.set_attitude_orbital(dcm_from_euler_zyx(*np.radians(spec.initial_ypr_deg)),
                                  np.radians(spec.initial_rate_dps))

    def set_attitude_orbital(self, R_bo: np.ndarray, omega_rel_radps: np.ndarray) -> None:
        """Put the body at attitude R_bo w.r.t. the orbital frame, rotating at `omega_rel_radps` relative
        to it (body axes), now; the truth history restarts here."""
        self.body.q = quat_from_dcm(self.orbital_frame(self.t_s) @ R_bo)
        self.body.omega_radps = orbital_rate_body_radps(R_bo, self.orbit.mean_motion_radps) + omega_rel_radps
        self._env_moment = self.env.torque_Nm(self.t_s, self.body.q)
        self._history.clear()
        self._history.append(self._snapshot())

    def orbital_frame(self, t_s: float) -> np.ndarray:
        """R_oi at `t_s`."""
        return orbital_frame_dcm(self.orbit.position_eci_m(t_s), self.orbit.velocity_eci_mps(t_s))

    def _step(self, h: float) -> None:
        """One step of body and kit: the scenario's moment plus the environment's (aerodynamic, gravity
        gradient, the kit's magnets) held over the step, then the kit advanced to the new time."""
        self.scenario.moment_Nm(self.t_s, out=self._moment)
        cache = getattr(self, "_b_eci_cache", None)
        b_eci = cache[1] if cache is not None and cache[0] == self.t_s else None
        self._env_moment = self.env.torque_Nm(self.t_s, self.body.q, b_eci)
        self.body.step(h, self._moment + self._env_moment)
        self.t_s += h
        self.kit.advance_to(self.t_s)

    def _snapshot(self) -> Truth:
        """As `Simulator._snapshot`, with the environment's torque in the moment; keeps B_ECI for the
        next step's torque (one field evaluation per step instead of two)."""
        b_eci = self.b_eci_T(self.t_s)
        self._b_eci_cache = (self.t_s, b_eci)
        q = self.body.q.copy()
        moment = self.scenario.moment_Nm(self.t_s).copy()
        env_moment = getattr(self, "_env_moment", None)
        if env_moment is not None:
            moment += env_moment
        return Truth(self.t_s, self.body.omega_radps.copy(), q, quat_to_dcm(q).T @ b_eci, moment)

    def extra_field_body_T(self, t_s: float) -> np.ndarray:
        """The kit's magnets at the sensor (`hil.kit_field`), from the channels' state now."""
        return self.kit_field.b_body_T()

    def attitude_orbital(self, t_s: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(R_bo, ω relative to the orbital frame in body axes, B in body axes) from the truth at `t_s`."""
        tr = self.truth(t_s)
        R_bo = self.orbital_frame(tr.t_s).T @ quat_to_dcm(tr.q_body_to_eci)
        w_rel = tr.omega_radps - orbital_rate_body_radps(R_bo, self.orbit.mean_motion_radps)
        return R_bo, w_rel, tr.b_body_T

    def b_orbital_T(self, t_s: np.ndarray) -> np.ndarray:
        """Field along the orbit in orbital axes at times `t_s` (N,) -> (N, 3) (the field model)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        r = self.orbit.position_eci_m(t)
        v = self.orbit.velocity_eci_mps(t)
        b = self.b_eci_T(t)
        z = -r / np.linalg.norm(r, axis=1, keepdims=True)
        x = v - np.einsum("ij,ij->i", v, z)[:, None] * z
        x /= np.linalg.norm(x, axis=1, keepdims=True)
        y = np.cross(z, x)
        return np.stack((np.einsum("ij,ij->i", b, x), np.einsum("ij,ij->i", b, y), np.einsum("ij,ij->i", b, z)),
                        axis=1)


class TruthAttitude:
    """The controller's attitude from the simulator's truth, with the field forecast from its field model
    and orbit — what lapkhanov2019 assumes (perfect attitude knowledge)."""

    description = "simulation truth (attitude, rate, field and field forecast), as the paper assumes"

    def __init__(self, sim: DeorbitSimulator) -> None:
        self.sim = sim

    def attitude(self, now_s: float) -> AttitudeInput:
        R_bo, w_rel, b_body = self.sim.attitude_orbital(self.sim.clock.true_s(now_s))
        return AttitudeInput(R_bo, w_rel, b_body, self.sim.b_orbital_T)


def controller_config(sim: DeorbitSimulator, **overrides):
    """The controller's configuration for this spacecraft: its orbit rate, dipole and aerodynamic
    stiffness (|r_cp|·½ρv²C_d·(S_sail + S_body)) from the scenario; `overrides` replace any field."""
    from fsw.deorbit.controller import ControllerConfig, aero_stiffness_Nm_per_rad

    env, orbit = sim.env, sim.orbit
    ka = aero_stiffness_Nm_per_rad(env.rho_kgm3, orbit.radius_m * orbit.mean_motion_radps, env.cd,
                                   env.sail_area_m2 + env.body_area_m2, float(np.linalg.norm(env.r_cp_body_m)))
    fields = dict(dipole_Am2=sim.spec.dipole_Am2, mean_motion_radps=orbit.mean_motion_radps,
                  aero_stiffness_Nm_per_rad=ka)
    fields.update(overrides)
    return ControllerConfig(**fields)


ATTITUDE_SOURCES = ("truth", "estimate")


def build_kit(sim: DeorbitSimulator, controller=None, law: str = "mpc", attitude: str = "truth",
              sigma_b_T: float = 1.5e-6, controller_overrides: dict | None = None, **kit_options):
    """The flight software's de-orbit kit for a SITL run: the emulator's lines, the controller's attitude
    from `attitude` ("truth": :class:`TruthAttitude`; "estimate": the box's own,
    `fsw.deorbit.onboard_attitude.EstimatedAttitude` with the sensor's σ `sigma_b_T` and the spacecraft as
    the box knows it, :func:`box_spacecraft`), and a controller configured for the scenario with `law`
    (:func:`controller_config`, with `controller_overrides` replacing any of its fields) unless `controller`
    is given."""
    from fsw.deorbit.kit import DeorbitKit
    from fsw.deorbit.onboard_attitude import EstimatedAttitude

    if attitude not in ATTITUDE_SOURCES:
        raise ValueError(f"attitude source must be one of {ATTITUDE_SOURCES}, got {attitude!r}")
    if controller is not None and controller_overrides:
        raise ValueError("give a controller configuration or overrides of the scenario's, not both")
    controller = controller or controller_config(sim, **{"law": law, **(controller_overrides or {})})
    source = (TruthAttitude(sim) if attitude == "truth" else
              EstimatedAttitude(sigma_b_T, box_spacecraft(sim.spec, controller.inertia_kgm2)))
    kit_options.setdefault("magnets", box_magnets(sim.spec))
    kit = DeorbitKit(sim.kit, source, controller=controller, **kit_options)
    kit.truth_ypr = lambda now_s: euler_zyx(sim.attitude_orbital(sim.clock.true_s(now_s))[0])
    return kit


def box_spacecraft(spec: DeorbitSpec, inertia_kgm2):
    """The spacecraft as the box knows it (`fsw.estimation.orbital_attitude.SpacecraftModel`): the design's
    sail, body area, drag coefficient and centre of pressure from the scenario, the controller's inertia
    (the design value: identifying it is a later phase of the mission), and for the density the
    exponential model the scenario names (the box's guess; here the same as the simulated atmosphere)."""
    from fsw.estimation.orbital_attitude import SpacecraftModel

    return SpacecraftModel(tuple(inertia_kgm2), spec.sail_area_m2, spec.body_area_m2, spec.drag_coefficient,
                           tuple(spec.cp_offset_m), density_kgm3=spec.density_kgm3,
                           density_ref_alt_km=spec.density_ref_alt_km,
                           density_scale_height_km=spec.density_scale_height_km)


def box_magnets(spec: DeorbitSpec):
    """The magnets as the box is configured for this spacecraft (`fsw.deorbit.kit_field.MagnetGeometry`):
    the scenario's positions, moment and leakage — the design; the truth may be changed after (a
    benchmark's manufacturing errors)."""
    from fsw.deorbit.kit_field import MagnetGeometry

    from .deorbit_kit import HOME_AXIS

    return tuple(MagnetGeometry(tuple(pos), tuple(float(x) for x in axis), spec.dipole_Am2,
                                leakage=spec.capsule_leakage)
                 for pos, axis in zip((spec.pitch_magnet_position_m, spec.yaw_magnet_position_m), HOME_AXIS))
