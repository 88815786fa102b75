"""The model of the output-error fit, and what it leaves to be fitted.

From an attitude q (body → ECI) and rate ω at a start time (physics-and-seeds.md §2):

    J ω̇ + ω × (J ω) = M(t) + p_m(t) × B_body + 3μ/r³ r̂ × (J r̂) + r_cp × F_drag,
    q̇ = ½ q ⊗ [0, ω],     B_body(t) = R(q)ᵀ B_I(t) + b

with M(t) the known applied moment (a tug: M = r × F, sedelnikov2023 eq. 6), p_m(t) the known dipole
of the box's magnets (M = p × B, lapkhanov2019 eq. 4), B_I(t) the inertial field along the orbit (a
field model), b a constant offset (sensor and host magnetisation), and the gravity gradient on the
body when the orbit is known (r̂ = R(q)ᵀ r_I/|r_I| the unit radius vector in body axes, μ the Earth's
gravitational parameter), and with the box's model of the spacecraft its aerodynamic moment
(F_drag = −½ρ|v|²C_d(S_sail|n·v̂| + S_body)v̂, v = R(q)ᵀ v_I the orbital velocity in body axes, the air
at rest in inertial axes as the de-orbit simulator has it); without an orbit the motion is taken as free
of both. :class:`KnownAction` holds M, p_m, the orbit and the spacecraft; :class:`InertiaParam` maps the
fitted parameters to the tensor J (full, diagonal, shape only or scale only) and to the moments of
unknown size.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import numpy as np

from .. import sampled_moment as sm
from ..field_motion import MU_EARTH_M3S2

if TYPE_CHECKING:
    from ..orbital_attitude import SpacecraftModel

FieldFn = Callable[[np.ndarray], np.ndarray]
"""B_I(t): inertial (ECI) field [T] at an array of times (m,) → (m, 3)."""

PositionFn = Callable[[np.ndarray], np.ndarray]
"""r_I(t): the orbit's position [m, inertial axes] at an array of times (m,) → (m, 3)."""

#: Inertia parametrisations and their number of parameters.
MODES = {"full": 6, "diag": 3, "shape": 5, "shape_diag": 2, "scale": 1}


# --- the known action --------------------------------------------------------------------------------

@dataclass(frozen=True)
class KnownAction:
    """Known applied action, piecewise constant: on [t_k, t_{k+1}) the moment ``moment_Nm[k]`` (body,
    about the centre of mass) and the magnets' dipole ``dipole_Am2[k]`` (body); zero before t_0. On each
    of ``unknown_intervals`` (t0, t1) a constant moment of unknown size (prior 1-σ (3,) in
    ``unknown_sigma_Nm``, inf or none: free) adds to ``moment_Nm``, fitted by :func:`identify`.
    ``orbit_position_m``: where the body is (r_I(t)); given, the gravity gradient joins the model
    (:meth:`with_orbit`). On a body of tens of kg·m² with moments ~10 kg·m² apart at 600 km it is
    ~2·10⁻⁵ N·m, a few % of the kit's magnets' moment, and acts throughout: left out, the fit puts its
    effect into the tensor. ``drag``: the box's model of the spacecraft (`orbital_attitude.SpacecraftModel`:
    its sail, body area, C_d, centre of pressure and atmosphere), its aerodynamic moment in the model too.
    On AMDS with its 5 m² sail at 600 km that is ~6·10⁻⁶ N·m, 1–2 % of the kit's magnets' moment; left out
    of the fit, on a mission record it moved the tensor by ~2 % of the largest moment."""

    t_s: np.ndarray
    moment_Nm: np.ndarray
    dipole_Am2: np.ndarray
    unknown_intervals: tuple = ()
    unknown_sigma_Nm: tuple = ()
    orbit_position_m: PositionFn | None = None
    drag: SpacecraftModel | None = None

    def with_orbit(self, position_m: PositionFn | None, drag: SpacecraftModel | None = None) -> "KnownAction":
        """This action on a body at `position_m` (r_I(t)): the gravity gradient in the model, and the
        aerodynamic moment of `drag` (None: without; both need the orbit)."""
        return dataclasses.replace(self, orbit_position_m=position_m,
                                   drag=drag if position_m is not None else None)

    def environment_vectors(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """At times `t` (m,) with the orbit: g(t) = √(3μ/|r|³) r_I/|r| (m, 3), so that the gravity-gradient
        moment is g_b × (J g_b) with g_b = R(q)ᵀ g; and with `drag`, v_I(t)·√(ρ(r)/ρ0) (m, 3) — the orbital
        velocity (a central difference of positions 1 s apart) scaled so that ρ0|v|² in the drag is
        ρ(r)|v|² at the orbit's altitude (else None)."""
        t = np.asarray(t, float)
        r = np.asarray(self.orbit_position_m(t), float).reshape(-1, 3)
        n = np.linalg.norm(r, axis=1, keepdims=True)
        g = r * np.sqrt(3.0 * MU_EARTH_M3S2 / n ** 3) / n
        if self.drag is None:
            return g, None
        v = (np.asarray(self.orbit_position_m(t + 0.5), float).reshape(-1, 3)
             - np.asarray(self.orbit_position_m(t - 0.5), float).reshape(-1, 3))
        rho = np.asarray(self.drag.density_at_kgm3(n[:, 0]), float)
        return g, v * np.sqrt(rho / self.drag.density_kgm3)[:, None]

    @staticmethod
    def none() -> "KnownAction":
        return KnownAction(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))

    @staticmethod
    def pulses(pulses=(), dipole_pulses=()) -> "KnownAction":
        """From (start_s, duration_s, vector) pulses of moment [N·m] and of dipole [A·m²] (summed)."""
        allp = [*pulses, *dipole_pulses]
        if not allp:
            return KnownAction.none()
        t = np.array(sorted({float(s) for s, d, _ in allp} | {float(s + d) for s, d, _ in allp}))
        m = np.zeros((len(t), 3))
        p = np.zeros((len(t), 3))
        for k, tk in enumerate(t):
            for s, d, v in pulses:
                if s <= tk < s + d:
                    m[k] += v
            for s, d, v in dipole_pulses:
                if s <= tk < s + d:
                    p[k] += v
        return KnownAction(t, m, p)

    @staticmethod
    def from_samples(t_s: np.ndarray, moment_Nm: np.ndarray, hold: str = "centered") -> "KnownAction":
        """From a moment sampled with the magnetometer (recording columns m*_Nm).

        ``hold="centered"``: each sample's moment holds from half a step before it to half a step after
        (switch instants unbiased on average); ``"forward"``: from the sample to the next one.
        A row with a NaN (a lost truth frame) is an unknown moment, never zero: held, or fitted on
        ``unknown_intervals`` (`sampled_moment.plan`).
        """
        t = np.asarray(t_s, float)
        pl = sm.plan(t, moment_Nm, hold)
        m = pl.moment_Nm
        change = np.flatnonzero(np.any(np.diff(m, axis=0) != 0, axis=1)) + 1
        idx = np.concatenate([[0], change]).astype(int)
        starts = t[idx].copy()
        if hold == "centered":
            starts[1:] = 0.5 * (t[idx[1:] - 1] + t[idx[1:]])
        starts[0] = -math.inf
        return KnownAction(starts, m[idx], np.zeros((len(idx), 3)), pl.intervals, pl.sigma_Nm)

    def _at(self, values: np.ndarray, t: np.ndarray) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t, float))
        i = np.searchsorted(self.t_s, t, side="right") - 1
        out = np.zeros((len(t), 3))
        ok = i >= 0
        out[ok] = values[i[ok]]
        return out

    def moment_at(self, t: np.ndarray) -> np.ndarray:
        return self._at(self.moment_Nm, t)

    def dipole_at(self, t: np.ndarray) -> np.ndarray:
        return self._at(self.dipole_Am2, t)

    def dipole_groups(self, t: np.ndarray) -> np.ndarray:
        """Per time in `t`: the index of the distinct non-zero dipole acting then (in order of first
        appearance), −1 where none acts. The magnets' field at the sensor is one per dipole state, so is
        its compensation's error (`FitOptions.kit_offset_sigma_T`)."""
        d = self.dipole_at(t)
        out = np.full(len(d), -1, int)
        on = np.any(d != 0, axis=1)
        if np.any(on):
            _, first, inv = np.unique(d[on], axis=0, return_index=True, return_inverse=True)
            out[on] = np.argsort(np.argsort(first))[inv.ravel()]
        return out

    def switch_times(self) -> np.ndarray:
        return self.t_s[np.isfinite(self.t_s)]

    def impulse_Nms(self, t0: float = -math.inf, t1: float = math.inf) -> np.ndarray:
        """∫M dt over [t0, t1] (the moment part only)."""
        edges = np.concatenate([self.t_s, [math.inf]])
        total = np.zeros(3)
        for k in range(len(self.t_s)):
            a, b = max(edges[k], t0), min(edges[k + 1], t1)
            if b > a and np.any(self.moment_Nm[k]):
                total += (b - a) * self.moment_Nm[k]
        return total

    def active(self, t0: float, t1: float) -> bool:
        """True when any moment or dipole acts somewhere in [t0, t1)."""
        edges = np.concatenate([self.t_s, [math.inf]])
        for k in range(len(self.t_s)):
            if min(edges[k + 1], t1) > max(edges[k], t0) and (np.any(self.moment_Nm[k])
                                                              or np.any(self.dipole_Am2[k])):
                return True
        return False


# --- parametrisation of the tensor ---------------------------------------------------------------------

#: Unknown moments are parametrised as θ_u = M / (I_ref · MOMENT_SCALE_RADPS2): order one for an
#: angular acceleration of 1e-3 rad/s² (0.2 N·m on Aist-2D's 200 kg·m²).
MOMENT_SCALE_RADPS2 = 1e-3


@dataclass
class InertiaParam:
    """Maps the global dynamic block of θ to the tensor components p (6,) and the unknown moments.

    θ_I = [tensor part | unknown moments]. The tensor part: p = T θ_I + c with ``full`` p/I_ref (6),
    ``diag`` (Ixx, Iyy, Izz)/I_ref (3), ``shape`` the tensor with Ixx fixed to I_ref (5: the others
    /I_ref), ``shape_diag`` (Iyy, Izz)/I_ref (2), ``scale`` the inverse θ = 1/κ of the scale κ of a fixed
    shape, p = p_shape/θ (1). Then one constant
    moment vector (3 parameters, N·m / (I_ref · MOMENT_SCALE_RADPS2)) per interval of
    ``unknown_intervals`` ((t0, t1) pairs, not overlapping): a torque known to act there but not known
    in size — e.g. a tug pulse, for a shape that must not rely on the torque's calibration; its prior
    1-σ (3,) [N·m] in ``moment_sigma_Nm`` (free when not given or inf).

    Why ``scale`` fits the inverse: with J = κ J_s the motion is J_s ω̇ + ω × J_s ω = (M + p_m × B)/κ —
    the gyroscopic part does not depend on κ and the known action's acceleration is linear in θ = 1/κ.
    θ = 0 is the torque-free motion and a sign change of θ reverses the action, a smooth path for the
    fit; in κ itself J is singular at κ = 0, a wall of infinite acceleration the fit cannot cross back
    once a step has jumped it (a loose first stage that sees little of the torque could end at κ < 0,
    and from there every stage drove κ towards −∞, the torque-free side nearest the data, ending
    unconverged at κ̂/κ of −40…−80).
    """

    mode: str
    I_ref: float
    p_shape: np.ndarray | None = None     # (R, 6) for "scale"
    unknown_intervals: tuple = ()
    moment_sigma_Nm: tuple = ()

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {sorted(MODES)}")
        if self.mode == "scale":
            self.p_shape = np.atleast_2d(np.asarray(self.p_shape, float))
        ui = tuple((float(a), float(b)) for a, b in self.unknown_intervals)
        if any(b <= a for a, b in ui) or any(ui[k + 1][0] < ui[k][1] for k in range(len(ui) - 1)):
            raise ValueError("unknown-moment intervals must be increasing, non-empty and not overlapping")
        self.unknown_intervals = ui

    @property
    def n_tensor(self) -> int:
        return MODES[self.mode]

    @property
    def n_moments(self) -> int:
        return 3 * len(self.unknown_intervals)

    @property
    def n(self) -> int:
        return self.n_tensor + self.n_moments

    @property
    def full(self) -> bool:
        return self.mode in ("full", "shape", "scale")

    @property
    def moment_scale_Nm(self) -> float:
        return self.I_ref * MOMENT_SCALE_RADPS2

    def subset(self, runs: np.ndarray) -> "InertiaParam":
        """The same parametrisation for the runs ``runs`` (their fixed shapes, mode "scale")."""
        if self.p_shape is None:
            return self
        return InertiaParam(self.mode, self.I_ref, self.p_shape[runs], self.unknown_intervals, self.moment_sigma_Nm)

    def jacobian(self, theta_I: np.ndarray, run: int = 0) -> np.ndarray:
        """∂p/∂θ_I (6, n) at θ_I (n,) (zero columns for the moments): T of :meth:`affine` for the modes
        linear in θ; for ``scale`` −p_shape/θ²."""
        if self.mode == "scale":
            T = np.zeros((6, self.n))
            T[:, 0] = -self.p_shape[run] / float(theta_I[0]) ** 2
            return T
        return self.affine(run)[0]

    def affine(self, run: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """T (6, n), c (6,) with p = T θ_I + c (zero columns for the moments); not for ``scale`` (p is
        not affine in θ there: :meth:`jacobian`, :meth:`to_p`)."""
        if self.mode == "scale":
            raise ValueError("the scale mode's p = p_shape/θ is not affine in θ")
        T = np.zeros((6, self.n))
        c = np.zeros(6)
        if self.mode == "full":
            T[:, :6] = np.eye(6) * self.I_ref
        elif self.mode == "diag":
            T[:3, :3] = np.eye(3) * self.I_ref
        elif self.mode == "shape":
            c[0] = self.I_ref
            T[1:, :5] = np.eye(5) * self.I_ref
        elif self.mode == "shape_diag":
            c[0] = self.I_ref
            T[1:3, :2] = np.eye(2) * self.I_ref
        return T, c

    def to_p(self, theta_I: np.ndarray, runs: np.ndarray) -> np.ndarray:
        """θ_I (nb, n) → p (nb, 6)."""
        if self.mode == "scale":
            with np.errstate(divide="ignore", invalid="ignore"):
                return self.p_shape[runs] / theta_I[:, :1]
        T, c = self.affine()
        return theta_I @ T.T + c

    def to_moments(self, theta_I: np.ndarray) -> np.ndarray | None:
        """θ_I (nb, n) → the unknown moments (K, 3, nb) [N·m], None when there are none."""
        if not self.n_moments:
            return None
        u = theta_I[:, self.n_tensor:].reshape(len(theta_I), -1, 3) * self.moment_scale_Nm
        return np.ascontiguousarray(u.transpose(1, 2, 0))

    def from_p(self, p: np.ndarray, run: int = 0, moments_Nm: np.ndarray | None = None) -> np.ndarray:
        """θ_I of a tensor p (and of the unknown moments (K, 3), zero when not given)."""
        th = np.zeros(self.n)
        nt = self.n_tensor
        if self.mode == "scale":
            ps = self.p_shape[run]
            th[0] = float(ps @ ps) / float(ps @ np.asarray(p, float))    # 1/κ, κ the least-squares scale
        else:
            T, c = self.affine(run)
            th[:nt] = np.linalg.lstsq(T[:, :nt], np.asarray(p, float) - c, rcond=None)[0]
        if moments_Nm is not None and self.n_moments:
            th[nt:] = np.asarray(moments_Nm, float).ravel() / self.moment_scale_Nm
        return th

    def moments_of(self, theta_I: np.ndarray, cov_I: np.ndarray | None = None):
        """The unknown moments (K, 3) [N·m] of one θ_I and their covariance (3K, 3K)."""
        nt, s = self.n_tensor, self.moment_scale_Nm
        m = np.asarray(theta_I[nt:], float).reshape(-1, 3) * s
        cov = None if cov_I is None else np.asarray(cov_I)[nt:, nt:] * s * s
        return m, cov
