"""Torques on the AMDS spacecraft in low orbit, and the orbital frame its attitude is measured in.

The spacecraft of lapkhanov2019 (Table 1): 180 kg, J = diag(17.995, 20.711, 15.269) kg·m², a 5 m² drag
sail, a 0.58 m² body, the centre of pressure 0.12 m from the centre of mass, two 15 A·m² magnets.

Orbital frame (o), the reference of yaw and pitch (a local-vertical/local-horizontal frame):

- x_o along the orbital velocity v: the direction of flight. The atmosphere flows past the spacecraft
  along −x_o (co-rotation of the atmosphere neglected, < 4° at 600 km).
- z_o towards nadir, −r/|r|.
- y_o = z_o × x_o, minus the orbit normal.

Body attitude w.r.t. the orbital frame: R_bo = Rz(ψ)·Ry(θ)·Rx(φ) (aerospace ZYX: yaw ψ about z_o, then
pitch θ about the new y, then roll φ about the new x), v_o = R_bo v_b. The sail's normal is body x; in the
orbital frame it is x_b = (cos θ cos ψ, cos θ sin ψ, −sin θ), which does not depend on roll: yaw and pitch
are exactly the azimuth and (minus) the elevation of the sail normal w.r.t. the flight direction, so
ψ = θ = 0 is the sail broadside to the flow whatever the (uncontrolled) roll. Positive pitch tilts the
sail normal up (towards zenith), positive yaw towards +y_o.

Torques (body axes, about the centre of mass):

- aerodynamic: flat-plate drag F = −½ ρ v² C_d (S_sail |n·v̂| + S_body) v̂ applied at the centre of pressure
  r_cp: M = r_cp × F. With r_cp = −0.12 m · x_b (behind the centre of mass) the torque turns the sail
  normal towards the flight direction (a shuttlecock / weathervane): restoring but undamped. Density from
  the exponential model of Vallado (Fundamentals of Astrodynamics and Applications, 4th ed., Table 8-4,
  CIRA-72 based): ρ = 1.454e-13 kg/m³ · exp(−(h − 600 km) / 71.835 km) for 600 ≤ h < 700 km.
- gravity gradient: M = 3 μ / r³ · r̂ × (J r̂), r̂ the unit radius vector in body axes.
- magnets (lapkhanov2019 eq. 4): M = p × B, p the sum of the unscreened dipoles in body axes.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from fsw.estimation.rotations import quat_to_dcm

from .field import FieldModel, b_eci_from_model_T
from .orbit import MU_EARTH_M3S2, CircularOrbit

__all__ = [
    "VALLADO_600KM",
    "ExponentialAtmosphere",
    "orbital_frame_dcm",
    "orbital_rate_body_radps",
    "euler_zyx_from_dcm",
    "dcm_from_euler_zyx",
    "aero_torque_Nm",
    "gravity_gradient_torque_Nm",
    "magnetic_torque_Nm",
    "Environment",
    "Torques",
]


@dataclass(frozen=True)
class ExponentialAtmosphere:
    """ρ(h) = ρ0 · exp(−(h − h0) / H) [kg/m³]."""

    rho0_kgm3: float
    h0_m: float
    scale_height_m: float

    def density_kgm3(self, altitude_m: float) -> float:
        return float(self.rho0_kgm3 * np.exp(-(altitude_m - self.h0_m) / self.scale_height_m))


VALLADO_600KM = ExponentialAtmosphere(1.454e-13, 600e3, 71.835e3)
"""Vallado Table 8-4, the 600-700 km band (mean solar activity)."""


def orbital_frame_dcm(r_eci_m: np.ndarray, v_eci_mps: np.ndarray) -> np.ndarray:
    """R_oi: columns x_o, y_o, z_o in ECI (v_inertial = R_oi v_orbital); see the module docstring."""
    z = -r_eci_m / np.linalg.norm(r_eci_m)
    x = v_eci_mps - np.dot(v_eci_mps, z) * z
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return np.column_stack((x, y, z))


def orbital_rate_body_radps(R_bo: np.ndarray, mean_motion_radps: float) -> np.ndarray:
    """Rate of the orbital frame w.r.t. inertial space in body axes: n about −y_o (circular orbit)."""
    return R_bo.T @ np.array([0.0, -mean_motion_radps, 0.0])


def euler_zyx_from_dcm(R_bo: np.ndarray) -> tuple[float, float, float]:
    """(yaw ψ, pitch θ, roll φ) [rad] of R_bo = Rz(ψ) Ry(θ) Rx(φ)."""
    yaw = float(np.arctan2(R_bo[1, 0], R_bo[0, 0]))
    pitch = float(-np.arcsin(np.clip(R_bo[2, 0], -1.0, 1.0)))
    roll = float(np.arctan2(R_bo[2, 1], R_bo[2, 2]))
    return yaw, pitch, roll


def dcm_from_euler_zyx(yaw_rad: float, pitch_rad: float, roll_rad: float) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll) (active rotations, right-handed)."""
    cy, sy = np.cos(yaw_rad), np.sin(yaw_rad)
    cp, sp = np.cos(pitch_rad), np.sin(pitch_rad)
    cr, sr = np.cos(roll_rad), np.sin(roll_rad)
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return rz @ ry @ rx


def aero_torque_Nm(v_body_mps: np.ndarray, rho_kgm3: float, cd: float, sail_area_m2: float,
                   sail_normal_body: np.ndarray, body_area_m2: float, r_cp_body_m: np.ndarray) -> np.ndarray:
    """M = r_cp × F with the drag F = −½ ρ |v|² C_d (S_sail |n·v̂| + S_body) v̂ (flat plate + body).

    `v_body_mps`: the spacecraft's velocity w.r.t. the air in body axes; `r_cp_body_m`: the centre of
    pressure relative to the centre of mass.
    """
    speed = float(np.linalg.norm(v_body_mps))
    if speed == 0.0:
        return np.zeros(3)
    v_hat = v_body_mps / speed
    area = sail_area_m2 * abs(float(np.dot(sail_normal_body, v_hat))) + body_area_m2
    force = -0.5 * rho_kgm3 * speed * speed * cd * area * v_hat
    return np.cross(r_cp_body_m, force)


def gravity_gradient_torque_Nm(r_body_m: np.ndarray, J_kgm2: np.ndarray) -> np.ndarray:
    """M = 3 μ / r³ · r̂ × (J r̂) (point-mass Earth), `r_body_m` the position from Earth's centre in body axes."""
    r = float(np.linalg.norm(r_body_m))
    r_hat = r_body_m / r
    return (3.0 * MU_EARTH_M3S2 / r**3) * np.cross(r_hat, J_kgm2 @ r_hat)


def magnetic_torque_Nm(p_body_Am2: np.ndarray, b_body_T: np.ndarray) -> np.ndarray:
    """lapkhanov2019 eq. 4: M = p × B [N·m]."""
    return np.cross(p_body_Am2, b_body_T)


@dataclass
class Torques:
    """The parts of the last torque evaluation (body axes, N·m)."""

    aero: np.ndarray
    gravity: np.ndarray
    magnets: np.ndarray

    @property
    def total(self) -> np.ndarray:
        return self.aero + self.gravity + self.magnets


class Environment:
    """Aerodynamic, gravity-gradient and magnet torques on a spacecraft on `orbit`.

    `dipole_body_Am2()` returns the magnets' unscreened dipole in body axes now (the kit emulator).
    """

    def __init__(self, orbit: CircularOrbit, field: FieldModel, J_kgm2: np.ndarray, *,
                 dipole_body_Am2: Callable[[], np.ndarray], sail_area_m2: float = 5.0,
                 body_area_m2: float = 0.58, cd: float = 2.2,
                 r_cp_body_m: tuple[float, float, float] | np.ndarray = (-0.12, 0.0, 0.0),
                 atmosphere: ExponentialAtmosphere = VALLADO_600KM, era0_rad: float = 0.0,
                 b_eci_T: Callable[[float], np.ndarray] | None = None) -> None:
        self.orbit = orbit
        self.field = field
        self.J_kgm2 = np.asarray(J_kgm2, dtype=float)
        self.dipole_body_Am2 = dipole_body_Am2
        self.sail_area_m2 = float(sail_area_m2)
        self.body_area_m2 = float(body_area_m2)
        self.cd = float(cd)
        self.r_cp_body_m = np.asarray(r_cp_body_m, dtype=float)
        self.atmosphere = atmosphere
        self.era0_rad = float(era0_rad)
        self._b_eci_fn = b_eci_T
        self.rho_kgm3 = atmosphere.density_kgm3(orbit.altitude_m)  # circular orbit: constant
        self.last = Torques(np.zeros(3), np.zeros(3), np.zeros(3))
        self._sail_normal = np.array([1.0, 0.0, 0.0])

    def b_eci_T(self, t_s: float) -> np.ndarray:
        if self._b_eci_fn is not None:  # the simulator's (tabulated) field along the orbit
            return self._b_eci_fn(t_s)
        return b_eci_from_model_T(self.field, self.orbit.position_eci_m(t_s), t_s, self.era0_rad)

    def torque_Nm(self, t_s: float, q_body_to_eci: np.ndarray, b_eci_T: np.ndarray | None = None) -> np.ndarray:
        """Total torque at `t_s` for the attitude `q_body_to_eci`; the parts are kept in `last`."""
        R_t = quat_to_dcm(q_body_to_eci).T  # inertial -> body
        r = self.orbit.position_eci_m(t_s)
        v = self.orbit.velocity_eci_mps(t_s)
        b = self.b_eci_T(t_s) if b_eci_T is None else b_eci_T
        b_body = R_t @ b
        self.last = Torques(
            aero_torque_Nm(R_t @ v, self.rho_kgm3, self.cd, self.sail_area_m2, self._sail_normal,
                           self.body_area_m2, self.r_cp_body_m),
            gravity_gradient_torque_Nm(R_t @ r, self.J_kgm2),
            magnetic_torque_Nm(self.dipole_body_Am2(), b_body))
        return self.last.total

    def attitude_orbital(self, t_s: float, q_body_to_eci: np.ndarray) -> np.ndarray:
        """R_bo (body -> orbital) at `t_s`."""
        R_oi = orbital_frame_dcm(self.orbit.position_eci_m(t_s), self.orbit.velocity_eci_mps(t_s))
        return R_oi.T @ quat_to_dcm(q_body_to_eci)
