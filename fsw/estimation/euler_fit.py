"""Output-error identification: Euler's equations and the attitude kinematics fitted to magnetometer samples.

The model (physics-and-seeds.md §2): from an attitude q (body → ECI) and rate ω at a start time,

    J ω̇ + ω × (J ω) = M(t) + p_m(t) × B_body,     q̇ = ½ q ⊗ [0, ω],     B_body(t) = R(q)ᵀ B_I(t) + b

with M(t) the known applied moment (a tug: M = r × F, sedelnikov2023 eq. 6), p_m(t) the known dipole
of the box's magnets (M = p × B, lapkhanov2019 eq. 4), B_I(t) the inertial field along the orbit (a
field model) and b a constant offset (sensor and host magnetisation). The parameters — the tensor J
(full, diagonal, shape only or scale only), the initial state and b — are those that make the
predicted B_body(t_k) closest to the measured samples, in least squares weighted by the sensor noise
σ_B. Fitting the samples themselves, rather than Euler's equations on rates differentiated from them,
removes the errors-in-variables bias of the linear methods (inertia.py): the only noisy quantity is
the measurement.

Torque-free data fix the tensor only up to scale (the motion is the same for λJ); a known torque
fixes it. A torque whose size is not to be relied on (the shape of the cellular-rotation-slowdown
paper, then κ from the known impulse) is modelled as a constant moment of unknown size on its
interval (``unknown_moments``): the record on both sides of it, and the interval itself, then all
serve the shape. :func:`cramer_rao` gives the covariance no unbiased estimator beats with the given
noise, sampling and record (the Fisher information at the truth). The attitude about B_I is fixed
only by the field's motion along the orbit (about twice the orbital rate), which is why the field
model is part of the model.

A single trajectory over a long record ("single shooting") has a small basin of attraction: a rate
that is slightly wrong early makes the prediction wrap around later. The fit therefore starts with
multiple shooting (Bock 1984): the record is cut into segments of a few tens of samples, each with its
own initial (q, ω), and the segments are tied together by continuity defects whose weights grow from
loose to tight; each segment first fits its own arc, then the defects bring in Euler's equations
(the rate change across a segment is what J predicts). The result is polished by single shooting, which
gives the estimate and its covariance s²(JᵀJ)⁻¹.

The chain of segments is fixed by the data only up to a rotation about the field: after the first
(loose) stage the segment attitudes are re-chained end to start, candidate chains wound about the
mean field direction at a few rates are carried through the tightening stages (the dynamics tell the
windings apart), and single shooting is started from a few angles about B_I(t₀); the lowest cost wins.

Implementation: RK4 between the sample times and the switch times of the known action, vectorised
over a batch of trajectories — every segment of every Monte-Carlo run, nominal and one forward-
difference perturbation per parameter (the Jacobian) — and Levenberg–Marquardt per run, vectorised
over runs. :func:`identify_steps` is a generator that yields every few integration steps
(``chunk``): the flight software advances it once per loop tick, inside the task's budget;
:func:`identify` runs it to the end.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from . import inertia as inr
from . import sampled_moment as sm

FieldFn = Callable[[np.ndarray], np.ndarray]
"""B_I(t): inertial (ECI) field [T] at an array of times (m,) → (m, 3)."""

#: Inertia parametrisations and their number of parameters.
MODES = {"full": 6, "diag": 3, "shape": 5, "shape_diag": 2, "scale": 1}


# --- the known action --------------------------------------------------------------------------------

@dataclass(frozen=True)
class KnownAction:
    """Known applied action, piecewise constant: on [t_k, t_{k+1}) the moment ``moment_Nm[k]`` (body,
    about the centre of mass) and the magnets' dipole ``dipole_Am2[k]`` (body); zero before t_0. On each
    of ``unknown_intervals`` (t0, t1) a constant moment of unknown size (prior 1-σ (3,) in
    ``unknown_sigma_Nm``, inf or none: free) adds to ``moment_Nm``, fitted by :func:`identify`."""

    t_s: np.ndarray
    moment_Nm: np.ndarray
    dipole_Am2: np.ndarray
    unknown_intervals: tuple = ()
    unknown_sigma_Nm: tuple = ()

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


# --- integration schedules for segments ------------------------------------------------------------

@dataclass
class Segments:
    """RK4 schedules of G segments run side by side, padded to a common number of steps (h = 0).

    Segment g starts at sample ``bounds[g]`` and ends at sample ``bounds[g+1]`` (for the last one the
    last sample); its local samples are those from its start to its end inclusive. Steps never cross a
    switch of the known action nor an end of an interval with an unknown moment (``unknown``: the
    interval of each step, −1 for none).
    """

    t_samples: np.ndarray
    bounds: np.ndarray          # (G + 1,) sample indices
    h: np.ndarray               # (T, G)
    moment: np.ndarray          # (T, G, 3)
    dipole: np.ndarray          # (T, G, 3)
    magnetic: np.ndarray        # (T,) any segment has a dipole at this step
    b_stage: np.ndarray         # (T, G, 3, 3) B_I at t, t + h/2, t + h (magnetic steps)
    rec: np.ndarray             # (T, G) local sample reached at the step's end, −1 if none
    b_local: np.ndarray         # (G, L, 3) B_I at the local samples
    n_local: np.ndarray         # (G,)
    steps: np.ndarray           # (G,) real steps per segment
    unknown: np.ndarray | None = None   # (T, G) unknown-moment interval of the step, −1 none

    @property
    def G(self) -> int:
        return len(self.n_local)

    @staticmethod
    def build(t_samples: np.ndarray, bounds, action: KnownAction, b_inertial: FieldFn,
              h_max_s: float = 1.0, b_samples: np.ndarray | None = None,
              unknown_intervals=()) -> "Segments":
        t = np.asarray(t_samples, float)
        if t.ndim != 1 or t.size < 2 or np.any(np.diff(t) <= 0):
            raise ValueError("sample times must be a strictly increasing 1-D array of 2 or more")
        bounds = np.asarray(bounds, int)
        if b_samples is None:
            b_samples = np.asarray(b_inertial(t), float).reshape(-1, 3)
        ui = np.asarray(unknown_intervals, float).reshape(-1, 2)
        sw = np.union1d(action.switch_times(), ui.ravel())
        G = len(bounds) - 1
        per = []
        for g in range(G):
            a, b = bounds[g], bounds[g + 1]
            ts = t[a:b + 1]
            knots = np.union1d(ts, sw[(sw > ts[0]) & (sw < ts[-1])])
            dk = np.diff(knots)
            nsub = np.maximum(1, np.ceil(dk / h_max_s - 1e-9)).astype(int)
            h = np.repeat(dk / nsub, nsub)
            first = np.repeat(np.cumsum(nsub) - nsub, nsub)
            t0 = np.repeat(knots[:-1], nsub) + (np.arange(h.size) - first) * h
            rec = np.full(h.size, -1)
            ends = np.cumsum(nsub) - 1                  # step index ending on knot j + 1
            loc = np.searchsorted(ts, knots[1:])
            hit = (loc < ts.size) & (np.abs(ts[np.minimum(loc, ts.size - 1)] - knots[1:]) < 1e-9)
            rec[ends[hit]] = loc[hit]
            per.append((h, t0, rec))
        T = max(len(p[0]) for p in per)
        L = int(max(bounds[1:] - bounds[:-1]) + 1)
        H = np.zeros((T, G))
        REC = np.full((T, G), -1)
        T0 = np.zeros((T, G))
        for g, (h, t0, rec) in enumerate(per):
            H[:len(h), g] = h
            T0[:len(h), g] = t0
            T0[len(h):, g] = t0[-1] + h[-1] if len(h) else t[bounds[g]]
            REC[:len(h), g] = rec
        mid = T0 + 0.5 * H
        moment = action.moment_at(mid.ravel()).reshape(T, G, 3)
        dipole = action.dipole_at(mid.ravel()).reshape(T, G, 3)
        dipole[H == 0] = 0.0
        moment[H == 0] = 0.0
        magnetic = np.any(dipole != 0, axis=(1, 2))
        b_stage = np.zeros((T, G, 3, 3))
        mag = np.any(dipole != 0, axis=2)
        if np.any(mag):
            ts = np.stack([T0[mag], mid[mag], T0[mag] + H[mag]], axis=1)
            b_stage[mag] = np.asarray(b_inertial(ts.ravel()), float).reshape(-1, 3, 3)
        b_local = np.zeros((G, L, 3))
        n_local = bounds[1:] - bounds[:-1] + 1
        for g in range(G):
            b_local[g, :n_local[g]] = b_samples[bounds[g]:bounds[g + 1] + 1]
        steps = np.array([len(p[0]) for p in per])
        unknown = None
        if len(ui):
            unknown = np.full((T, G), -1)
            for k, (u0, u1) in enumerate(ui):
                unknown[(mid > u0) & (mid < u1) & (H > 0)] = k
        return Segments(t, bounds, H, moment, dipole, magnetic, b_stage, REC, b_local, n_local, steps, unknown)


def segment_bounds(n: int, length: int) -> np.ndarray:
    """Cut n samples into segments of about ``length`` samples (the last one absorbs the remainder)."""
    length = max(2, int(length))
    G = max(1, (n - 1) // length)
    return np.round(np.linspace(0, n - 1, G + 1)).astype(int)


# --- batched dynamics ---------------------------------------------------------------------------

def _inv_sym(J: np.ndarray) -> np.ndarray:
    """Inverse components of symmetric tensors given as (6, nb) [11, 22, 33, 12, 13, 23]."""
    a, d, f, b, c, e = J
    A = d * f - e * e
    B = c * e - b * f
    C = b * e - c * d
    det = a * A + b * B + c * C
    return np.array([A, a * f - c * c, a * d - b * b, B, C, b * c - a * e]) / det


def body_from_inertial(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """R(q)ᵀ v for unit quaternions q (4, nb) and v (3,) or (3, nb) → (3, nb)."""
    w, x, y, z = q
    v0, v1, v2 = v[0], v[1], v[2]
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    return np.array([
        (1 - 2 * (yy + zz)) * v0 + 2 * (xy + wz) * v1 + 2 * (xz - wy) * v2,
        2 * (xy - wz) * v0 + (1 - 2 * (xx + zz)) * v1 + 2 * (yz + wx) * v2,
        2 * (xz + wy) * v0 + 2 * (yz - wx) * v1 + (1 - 2 * (xx + yy)) * v2,
    ])


def _deriv(y: np.ndarray, J: np.ndarray, K: np.ndarray, M, dip, b_I) -> np.ndarray:
    """d/dt of y = [q (4), ω (3)] (7, nb); J, K = J⁻¹ as (6, nb) components; M (3,) or (3, nb)."""
    qw, qx, qy, qz, p, q, r = y
    J11, J22, J33, J12, J13, J23 = J
    K11, K22, K33, K12, K13, K23 = K
    H1 = J11 * p + J12 * q + J13 * r
    H2 = J12 * p + J22 * q + J23 * r
    H3 = J13 * p + J23 * q + J33 * r
    Mx, My, Mz = M[0], M[1], M[2]
    if dip is not None:
        bx, by, bz = body_from_inertial(y[:4], b_I)
        Mx = Mx + dip[1] * bz - dip[2] * by
        My = My + dip[2] * bx - dip[0] * bz
        Mz = Mz + dip[0] * by - dip[1] * bx
    e1 = Mx - (q * H3 - r * H2)
    e2 = My - (r * H1 - p * H3)
    e3 = Mz - (p * H2 - q * H1)
    return np.array([
        0.5 * (-qx * p - qy * q - qz * r),
        0.5 * (qw * p + qy * r - qz * q),
        0.5 * (qw * q - qx * r + qz * p),
        0.5 * (qw * r + qx * q - qy * p),
        K11 * e1 + K12 * e2 + K13 * e3,
        K12 * e1 + K22 * e2 + K23 * e3,
        K13 * e1 + K23 * e2 + K33 * e3,
    ])


class Pass:
    """One propagation of a batch of trajectories through their segments, resumable.

    ``group`` (nb,) segment of each trajectory; ``J6`` (6, nb); ``q0`` (4, nb); ``w0`` (3, nb);
    ``bias`` (3, nb); ``u`` (K, 3, nb) the moments [N·m] on the segments' unknown-moment intervals
    (``seg.unknown``), added to the known one. When :meth:`advance` returns True, ``pred`` (nb, L, 3)
    holds the predicted field at each trajectory's local samples, ``y`` (7, nb) the end states, and
    ``states`` (nb, L, 7) the states at the samples when ``keep_states``.
    """

    def __init__(self, seg: Segments, group: np.ndarray, J6: np.ndarray, q0: np.ndarray, w0: np.ndarray,
                 bias: np.ndarray, keep_states: bool = False, u: np.ndarray | None = None) -> None:
        self.seg = seg
        self.g = np.asarray(group, int)
        self.single = bool(np.all(self.g == self.g[0]))
        self.u = u if (u is not None and seg.unknown is not None and u.shape[0]) else None
        self.J = J6
        with np.errstate(divide="ignore", invalid="ignore"):
            self.K = _inv_sym(J6)
        nb = J6.shape[1]
        self.y = np.concatenate([q0, w0]).astype(float)
        self.bias = bias
        L = seg.b_local.shape[1]
        self.pred = np.full((nb, L, 3), np.nan)
        self.keep = keep_states
        self.states = np.full((nb, L, 7), np.nan) if keep_states else None
        self.i = 0
        self.n_steps = int(seg.steps[np.unique(self.g)].max())
        if self.single:
            self._record_all(0)
        else:
            self._record(np.arange(nb), np.zeros(nb, int))

    def _record(self, traj: np.ndarray, loc: np.ndarray) -> None:
        bI = self.seg.b_local[self.g[traj], loc].T                        # (3, m)
        b = body_from_inertial(self.y[:4, traj], bI) + self.bias[:, traj]
        self.pred[traj, loc, :] = b.T
        if self.keep:
            self.states[traj, loc, :] = self.y[:, traj].T

    def _record_all(self, k: int) -> None:
        b = body_from_inertial(self.y[:4], self.seg.b_local[self.g[0], k]) + self.bias
        self.pred[:, k, :] = b.T
        if self.keep:
            self.states[:, k, :] = self.y.T

    @property
    def done(self) -> bool:
        return self.i >= self.n_steps

    def advance(self, max_steps: int | None = None) -> bool:
        """Integrate up to ``max_steps`` more steps (all when None); True when the pass is complete."""
        s = self.seg
        stop = self.n_steps if max_steps is None else min(self.n_steps, self.i + int(max_steps))
        y, J, K, g = self.y, self.J, self.K, self.g
        g0 = int(g[0])
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            for i in range(self.i, stop):
                if self.single:
                    h = s.h[i, g0]
                    M = s.moment[i, g0]
                    rec = s.rec[i, g0]
                    if self.u is not None and s.unknown[i, g0] >= 0:
                        M = M[:, None] + self.u[s.unknown[i, g0]]
                else:
                    h = s.h[i, g]
                    M = s.moment[i, g].T
                    rec = s.rec[i, g]
                    if self.u is not None:
                        k = s.unknown[i, g]
                        on = k >= 0
                        if np.any(on):
                            M = M.copy()
                            M[:, on] += self.u[k[on], :, np.flatnonzero(on)].T
                if s.magnetic[i]:
                    dip = s.dipole[i, g].T
                    bs = s.b_stage[i, g]                                     # (nb, 3, 3)
                    k1 = _deriv(y, J, K, M, dip, bs[:, 0].T)
                    k2 = _deriv(y + (0.5 * h) * k1, J, K, M, dip, bs[:, 1].T)
                    k3 = _deriv(y + (0.5 * h) * k2, J, K, M, dip, bs[:, 1].T)
                    k4 = _deriv(y + h * k3, J, K, M, dip, bs[:, 2].T)
                else:
                    k1 = _deriv(y, J, K, M, None, None)
                    k2 = _deriv(y + (0.5 * h) * k1, J, K, M, None, None)
                    k3 = _deriv(y + (0.5 * h) * k2, J, K, M, None, None)
                    k4 = _deriv(y + h * k3, J, K, M, None, None)
                y = y + (h / 6.0) * (k1 + 2.0 * (k2 + k3) + k4)
                y[:4] /= np.sqrt(np.sum(y[:4] ** 2, axis=0))
                self.y = y
                if self.single:
                    if rec >= 0:
                        self._record_all(rec)
                else:
                    ok = rec >= 0
                    if np.any(ok):
                        self._record(np.flatnonzero(ok), rec[ok])
        self.i = stop
        return self.done


# --- quaternions ----------------------------------------------------------------------------------

def quat_exp(v: np.ndarray) -> np.ndarray:
    """Unit quaternion(s) (..., 4) of rotation vector(s) v (..., 3)."""
    v = np.asarray(v, float)
    a = np.linalg.norm(v, axis=-1, keepdims=True)
    small = a < 1e-12
    s = np.where(small, 0.5, np.sin(0.5 * a) / np.where(small, 1.0, a))
    return np.concatenate([np.cos(0.5 * a), s * v], axis=-1)


def quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product p ⊗ q for (..., 4) arrays, scalar first."""
    pw, px, py, pz = np.moveaxis(np.asarray(p, float), -1, 0)
    qw, qx, qy, qz = np.moveaxis(np.asarray(q, float), -1, 0)
    return np.stack([pw * qw - px * qx - py * qy - pz * qz, pw * qx + px * qw + py * qz - pz * qy,
                     pw * qy - px * qz + py * qw + pz * qx, pw * qz + px * qy - py * qx + pz * qw], axis=-1)


def quat_conj(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, float)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def _dcm(q: np.ndarray) -> np.ndarray:
    """R(q) (..., 3, 3) body → inertial of quaternions (..., 4)."""
    w, x, y, z = np.moveaxis(np.asarray(q, float), -1, 0)
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


def quat_aligning(b_body: np.ndarray, b_inertial: np.ndarray, angle_about_b_rad: float = 0.0) -> np.ndarray:
    """A body → inertial quaternion with R b̂_body = b̂_inertial, turned by an angle about B_I (the angle a
    single vector cannot fix)."""
    u = np.asarray(b_body, float) / np.linalg.norm(b_body)
    v = np.asarray(b_inertial, float) / np.linalg.norm(b_inertial)
    c = float(np.clip(u @ v, -1.0, 1.0))
    axis = np.cross(u, v)
    s = np.linalg.norm(axis)
    if s < 1e-9:
        perp = np.cross(u, [1.0, 0, 0]) if abs(u[0]) < 0.9 else np.cross(u, [0, 1.0, 0])
        axis = perp / np.linalg.norm(perp) * (0.0 if c > 0 else math.pi)
    else:
        axis = axis / s * math.atan2(s, c)
    return quat_mul(quat_exp(v * angle_about_b_rad), quat_exp(axis))


def retilt(q: np.ndarray, b_body: np.ndarray, b_inertial: np.ndarray) -> np.ndarray:
    """q turned by the smallest inertial rotation that makes R(q) b̂_body ∥ B_I (keeps the angle about B)."""
    R_b = body_from_inertial(quat_conj(q)[:, None], np.asarray(b_body, float))[:, 0]   # R(q) b_body
    u = R_b / np.linalg.norm(R_b)
    v = np.asarray(b_inertial, float) / np.linalg.norm(b_inertial)
    axis = np.cross(u, v)
    s = np.linalg.norm(axis)
    if s < 1e-12:
        return q
    return quat_mul(quat_exp(axis / s * math.atan2(s, float(u @ v))), q)


# --- parametrisation of the tensor ---------------------------------------------------------------------

#: Unknown moments are parametrised as θ_u = M / (I_ref · MOMENT_SCALE_RADPS2): order one for an
#: angular acceleration of 1e-3 rad/s² (0.2 N·m on Aist-2D's 200 kg·m²).
MOMENT_SCALE_RADPS2 = 1e-3


@dataclass
class InertiaParam:
    """Maps the global dynamic block of θ to the tensor components p (6,) and the unknown moments.

    θ_I = [tensor part | unknown moments]. The tensor part: p = T θ_I + c with ``full`` p/I_ref (6),
    ``diag`` (Ixx, Iyy, Izz)/I_ref (3), ``shape`` the tensor with Ixx fixed to I_ref (5: the others
    /I_ref), ``shape_diag`` (Iyy, Izz)/I_ref (2), ``scale`` κ with p = κ·p_shape (1). Then one constant
    moment vector (3 parameters, N·m / (I_ref · MOMENT_SCALE_RADPS2)) per interval of
    ``unknown_intervals`` ((t0, t1) pairs, not overlapping): a torque known to act there but not known
    in size — e.g. a tug pulse, for a shape that must not rely on the torque's calibration; its prior
    1-σ (3,) [N·m] in ``moment_sigma_Nm`` (free when not given or inf).
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

    def affine(self, run: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """T (6, n), c (6,) with p = T θ_I + c (zero columns for the moments)."""
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
        else:
            T[:, 0] = self.p_shape[run]
        return T, c

    def to_p(self, theta_I: np.ndarray, runs: np.ndarray) -> np.ndarray:
        """θ_I (nb, n) → p (nb, 6)."""
        if self.mode == "scale":
            return theta_I[:, :1] * self.p_shape[runs]
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
        T, c = self.affine(run)
        th = np.zeros(self.n)
        nt = self.n_tensor
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


# --- normal matrices -----------------------------------------------------------------------------

class Dense:
    """Batched dense normal matrices A (R, P, P) (single shooting)."""

    def __init__(self, A: np.ndarray) -> None:
        self.A = A

    def take(self, idx) -> "Dense":
        return Dense(self.A[idx].copy())

    def put(self, idx, other: "Dense") -> None:
        self.A[idx] = other.A

    def diag(self) -> np.ndarray:
        return np.diagonal(self.A, axis1=1, axis2=2).copy()

    def matvec(self, x: np.ndarray) -> np.ndarray:
        return np.einsum("rij,rj->ri", self.A, x)

    def solve(self, b: np.ndarray, extra_diag: np.ndarray) -> np.ndarray:
        A = self.A.copy()
        i = np.arange(A.shape[1])
        A[:, i, i] += extra_diag
        return np.linalg.solve(A, b[..., None])[..., 0]

    def inverse(self, extra_diag: np.ndarray) -> np.ndarray:
        A = self.A.copy()
        i = np.arange(A.shape[1])
        A[:, i, i] += extra_diag
        return np.linalg.pinv(A)


class BlockArrow:
    """Batched normal matrices of multiple shooting, kept in their sparse form.

    Per run: diagonal blocks ``D`` (G, 6, 6) of the segments' own parameters, blocks ``E`` (G−1, 6, 6)
    coupling segment g to g+1 (the defects), ``C`` (G, 6, m) coupling the segments to the m global
    parameters (tensor and offset) and ``Dm`` (m, m). Solved by block elimination (block Thomas for the
    tridiagonal part, then the Schur complement of the globals) — O(G) small solves instead of one
    dense (6G + m)² system.
    """

    def __init__(self, D, E, C, Dm, seg_idx: np.ndarray, glob_idx: np.ndarray) -> None:
        self.D, self.E, self.C, self.Dm = D, E, C, Dm
        self.seg_idx, self.glob_idx = seg_idx, glob_idx

    def take(self, idx) -> "BlockArrow":
        return BlockArrow(self.D[idx].copy(), self.E[idx].copy(), self.C[idx].copy(), self.Dm[idx].copy(),
                          self.seg_idx, self.glob_idx)

    def put(self, idx, o: "BlockArrow") -> None:
        self.D[idx], self.E[idx], self.C[idx], self.Dm[idx] = o.D, o.E, o.C, o.Dm

    def diag(self) -> np.ndarray:
        R = self.D.shape[0]
        out = np.zeros((R, self.seg_idx.size + self.glob_idx.size))
        out[:, self.seg_idx.ravel()] = np.diagonal(self.D, axis1=2, axis2=3).reshape(R, -1)
        out[:, self.glob_idx] = np.diagonal(self.Dm, axis1=1, axis2=2)
        return out

    def matvec(self, x: np.ndarray) -> np.ndarray:
        xs = x[:, self.seg_idx]                       # (R, G, 6)
        xm = x[:, self.glob_idx]                      # (R, m)
        ys = np.einsum("rgij,rgj->rgi", self.D, xs) + np.einsum("rgij,rj->rgi", self.C, xm)
        ys[:, :-1] += np.einsum("rgij,rgj->rgi", self.E, xs[:, 1:])
        ys[:, 1:] += np.einsum("rgji,rgj->rgi", self.E, xs[:, :-1])
        ym = np.einsum("rij,rj->ri", self.Dm, xm) + np.einsum("rgji,rgj->ri", self.C, xs)
        out = np.zeros_like(x)
        out[:, self.seg_idx] = ys
        out[:, self.glob_idx] = ym
        return out

    def _tri_solve(self, D: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """Solve the block-tridiagonal system (diagonal D, couplings E) for rhs (R, G, 6, c)."""
        G = D.shape[1]
        Dh = np.empty_like(D)
        Y = np.empty_like(rhs)
        Dh[:, 0], Y[:, 0] = D[:, 0], rhs[:, 0]
        for g in range(1, G):
            Lg = np.linalg.solve(Dh[:, g - 1], self.E[:, g - 1]).swapaxes(1, 2)   # Eᵀ Dh⁻¹ (Dh symmetric)
            Dh[:, g] = D[:, g] - Lg @ self.E[:, g - 1]
            Y[:, g] = rhs[:, g] - Lg @ Y[:, g - 1]
        X = np.empty_like(rhs)
        X[:, G - 1] = np.linalg.solve(Dh[:, G - 1], Y[:, G - 1])
        for g in range(G - 2, -1, -1):
            X[:, g] = np.linalg.solve(Dh[:, g], Y[:, g] - self.E[:, g] @ X[:, g + 1])
        return X

    def _schur(self, extra_diag: np.ndarray):
        D = self.D.copy()
        i6 = np.arange(6)
        D[:, :, i6, i6] += extra_diag[:, self.seg_idx]
        Dm = self.Dm.copy()
        im = np.arange(Dm.shape[1])
        Dm[:, im, im] += extra_diag[:, self.glob_idx]
        TinvC = self._tri_solve(D, self.C)                                   # (R, G, 6, m)
        S = Dm - np.einsum("rgim,rgin->rmn", self.C, TinvC)
        return D, S, TinvC

    def solve(self, b: np.ndarray, extra_diag: np.ndarray) -> np.ndarray:
        D, S, TinvC = self._schur(extra_diag)
        bs = b[:, self.seg_idx]
        Tb = self._tri_solve(D, bs[..., None])[..., 0]                      # (R, G, 6)
        rm = b[:, self.glob_idx] - np.einsum("rgim,rgi->rm", self.C, Tb)
        xm = np.linalg.solve(S, rm[..., None])[..., 0]
        xs = Tb - np.einsum("rgim,rm->rgi", TinvC, xm)
        out = np.zeros_like(b)
        out[:, self.seg_idx] = xs
        out[:, self.glob_idx] = xm
        return out

# --- Levenberg–Marquardt, vectorised over runs ---------------------------------------------------

@dataclass
class Prior:
    """Independent Gaussian priors on entries of θ: θ_i ~ N(mean_i, sigma_i²); sigma_i = inf means none.

    They regularise what the data do not fix yet — the scale before any torque, the offset against the
    attitude over a short arc — and are negligible once the data fix them."""

    mean: np.ndarray
    sigma: np.ndarray

    def __post_init__(self) -> None:
        self.mean = np.asarray(self.mean, float)
        self.sigma = np.asarray(self.sigma, float)
        self.w = np.where(np.isfinite(self.sigma), 1.0 / self.sigma, 0.0)

    def residual(self, theta: np.ndarray) -> np.ndarray:
        return np.where(self.w > 0, (theta - self.mean) * self.w, 0.0)

    def cost(self, theta: np.ndarray) -> np.ndarray:
        r = self.residual(theta)
        return np.sum(r * r, axis=-1)


@dataclass
class LMRuns:
    """Levenberg–Marquardt state of R runs (scaled parameters θ (R, P))."""

    theta: np.ndarray
    cost: np.ndarray = None          # data + prior (+ defects) at θ
    data_cost: np.ndarray = None     # measurement part of χ²
    A: object = None                 # Dense | BlockArrow at θ
    g: np.ndarray = None             # Jᵀr at θ
    dof: int = 1
    iterations: np.ndarray = None
    converged: np.ndarray = None

    def __post_init__(self) -> None:
        R = len(self.theta)
        self.cost = np.full(R, np.inf)
        self.data_cost = np.full(R, np.nan)
        self.iterations = np.zeros(R, int)
        self.converged = np.zeros(R, bool)


#: Fixed cost of one integration step in units of trajectory-steps (measured: ~190 µs per step plus
#: ~0.15 µs per trajectory with numpy on a laptop-class core).
STEP_OVERHEAD = 1300


def complete(gen):
    """Run a generator of this module to its end and return its value."""
    while True:
        try:
            next(gen)
        except StopIteration as stop:
            return stop.value


def evaluate_steps(problem, thetas: np.ndarray, runs: np.ndarray, chunk: int | None):
    """Generator: one evaluation of ``problem`` (cost, data cost, normal matrix, gradient, dof), yielding
    after every ``chunk`` units of work (never when ``chunk`` is None). A unit is one trajectory-step;
    each integration step also costs ``STEP_OVERHEAD`` units (its fixed cost in numpy calls), so a
    slice takes about the same time whatever the batch size."""
    ps, ctx = problem.begin(thetas, runs)
    if chunk is None:
        ps.advance()
        return problem.finish(ps, ctx)
    steps = max(1, int(chunk) // (ps.y.shape[1] + STEP_OVERHEAD))
    while not ps.advance(steps):
        yield
    yield
    out = problem.finish(ps, ctx)
    yield
    return out


def lm_steps(problem, runs: LMRuns, prior: Prior | None, max_iter: int, tol: float = 1e-3,
             rtol: float = 0.0, frozen: np.ndarray | None = None, chunk: int | None = None):
    """Levenberg–Marquardt on every run of ``problem`` (a generator; see :func:`lm`)."""
    R, P = runs.theta.shape
    w2 = prior.w ** 2 if prior is not None else np.zeros(P)
    lam = np.full(R, 1e-3)
    nu = np.full(R, 2.0)
    first = np.ones(R, bool)
    trial = runs.theta.copy()
    runs.converged[:] = False
    runs.cost[:] = np.inf
    for _ in range(max_iter):
        act = np.flatnonzero(~runs.converged)
        if act.size == 0:
            break
        c, dc, A, g, dof = yield from evaluate_steps(problem, trial[act], act, chunk)
        if prior is not None:
            c = c + prior.cost(trial[act])
        runs.iterations[act] += 1
        ok = np.isfinite(c)
        acc = ok & (first[act] | (c <= runs.cost[act]))
        gain = runs.cost[act] - c
        idx = act[acc]
        if idx.size:
            runs.theta[idx] = trial[idx]
            runs.cost[idx], runs.data_cost[idx] = c[acc], dc[acc]
            if runs.A is None:
                runs.A = A.take(np.zeros(R, int))
                runs.g = np.zeros((R, P))
            runs.A.put(idx, A.take(np.flatnonzero(acc)))
            runs.g[idx] = g[acc]
            runs.dof = dof
            lam[idx] = np.maximum(lam[idx] / 3.0, 1e-9)
            nu[idx] = 2.0
            done = acc & ~first[act] & (gain < tol + rtol * c)
            runs.converged[act[done]] = True
        fail = first[act] & ~ok
        runs.converged[act[fail]] = True
        rej = act[~acc & ~first[act]]
        lam[rej] *= nu[rej]
        nu[rej] *= 2.0
        runs.converged[rej[lam[rej] > 1e10]] = True
        first[act] = False
        step = np.flatnonzero(~runs.converged)
        if step.size == 0:
            break
        Ab = runs.A.take(step)
        gt = runs.g[step] + (prior.w * prior.residual(runs.theta[step]) if prior is not None else 0.0)
        d = Ab.diag() + w2
        dmax = np.maximum(d.max(axis=1, keepdims=True), 1.0)
        damp = w2 + lam[step, None] * np.maximum(d, 1e-9 * dmax)
        if frozen is not None:
            damp = damp + frozen * 1e12 * dmax
        delta = -Ab.solve(gt, damp)
        delta = np.where(np.isfinite(delta), delta, 0.0)
        if frozen is not None:
            delta[:, frozen] = 0.0
        Ad = Ab.matvec(delta) + w2 * delta
        pred = -(2 * np.sum(gt * delta, axis=1) + np.sum(delta * Ad, axis=1))
        runs.converged[step[~(pred >= 0.1 * (tol + rtol * runs.cost[step]))]] = True
        trial[step] = runs.theta[step] + delta
    return runs


def lm(problem, runs: LMRuns, prior: Prior | None, max_iter: int, tol: float = 1e-3, rtol: float = 0.0,
       frozen: np.ndarray | None = None) -> LMRuns:
    """Levenberg–Marquardt on every run of ``problem`` (``begin``/``finish`` → cost, data cost, A, g, dof).

    Restarts at the current θ (the problem may have changed: weights, data). A run stops when an
    accepted step gains less than ``tol`` + ``rtol``·cost (χ² units), when the predicted gain is below
    a tenth of that, or when the damping explodes. Marquardt damping λ·diag(A); ``frozen`` (P,) bool
    marks parameters kept where they are.
    """
    return complete(lm_steps(problem, runs, prior, max_iter, tol, rtol, frozen))


# --- single shooting ----------------------------------------------------------------------------------

class SingleShooting:
    """One trajectory per run over the first ``n`` samples: θ = [θ_I | ω₀/ω_s (3) | δθ₀ (3) | b/σ_B (3)].

    ``q_ref`` (R, 4) the attitude the rotation vector δθ₀ perturbs (body side); ``b_meas`` (R, n_all, 3).
    """

    def __init__(self, t_s: np.ndarray, b_meas: np.ndarray, b_samples: np.ndarray, action: KnownAction,
                 b_inertial: FieldFn, inertia: InertiaParam, q_ref: np.ndarray, sigma_b_T: float, *,
                 n: int | None = None, fit_bias: bool = True, omega_scale: float = 0.01,
                 h_max_s: float = 1.0, fd_step: float = 1e-6) -> None:
        self.t = np.asarray(t_s, float)
        self.n = len(self.t) if n is None else int(n)
        self.b_meas = np.asarray(b_meas, float)
        self.inertia = inertia
        self.q_ref = np.atleast_2d(np.asarray(q_ref, float)).copy()
        self.sigma = float(sigma_b_T)
        self.fit_bias = fit_bias
        self.omega_scale = omega_scale
        self.step = fd_step
        self.seg = Segments.build(self.t[:self.n], [0, self.n - 1], action, b_inertial, h_max_s,
                                  b_samples=np.asarray(b_samples)[:self.n],
                                  unknown_intervals=inertia.unknown_intervals)

    @property
    def n_params(self) -> int:
        return self.inertia.n + 6 + (3 if self.fit_bias else 0)

    def unpack(self, theta: np.ndarray, runs: np.ndarray):
        n = self.inertia.n
        p = self.inertia.to_p(theta[:, :n], runs)
        w0 = theta[:, n:n + 3] * self.omega_scale
        q0 = quat_mul(self.q_ref[runs], quat_exp(theta[:, n + 3:n + 6]))
        bias = theta[:, n + 6:n + 9] * self.sigma if self.fit_bias else np.zeros((len(theta), 3))
        return p, q0, w0, bias

    def start(self, thetas: np.ndarray, runs: np.ndarray, keep_states: bool = False) -> Pass:
        p, q0, w0, bias = self.unpack(thetas, runs)
        return Pass(self.seg, np.zeros(len(thetas), int), p.T, q0.T, w0.T, bias.T, keep_states,
                    u=self.inertia.to_moments(thetas[:, :self.inertia.n]))

    def begin(self, thetas: np.ndarray, runs: np.ndarray) -> tuple[Pass, tuple]:
        R, k = thetas.shape
        th = np.repeat(thetas[:, None, :], k + 1, axis=1)
        th[:, 1:, :] += self.step * np.eye(k)[None]
        return self.start(th.reshape(-1, k), np.repeat(runs, k + 1)), (runs, R, k)

    def evaluate(self, thetas: np.ndarray, runs: np.ndarray):
        return complete(evaluate_steps(self, thetas, runs, None))

    def finish(self, ps: Pass, ctx: tuple):
        runs, R, k = ctx
        n = self.n
        pred = ps.pred[:, :n].reshape(R, k + 1, n, 3)
        r = ((pred[:, 0] - self.b_meas[runs, :n]) / self.sigma).reshape(R, -1)
        Jm = ((pred[:, 1:] - pred[:, :1]) / (self.step * self.sigma)).reshape(R, k, -1)
        bad = ~(np.all(np.isfinite(r), axis=1) & np.all(np.isfinite(Jm), axis=(1, 2)))
        r = np.where(bad[:, None], 0.0, r)
        Jm = np.where(bad[:, None, None], 0.0, Jm)
        cost = np.where(bad, np.inf, np.sum(r * r, axis=1))
        return (cost, cost, Dense(np.einsum("rkm,rlm->rkl", Jm, Jm)), np.einsum("rkm,rm->rk", Jm, r),
                max(3 * n - k, 1))

    def trajectory(self, theta: np.ndarray, run: int = 0) -> dict:
        ps = self.start(theta[None, :], np.array([run]), keep_states=True)
        ps.advance()
        st = ps.states[0, :self.n]
        return {"b_body_T": ps.pred[0, :self.n], "q": st[:, :4], "omega_radps": st[:, 4:]}


# --- multiple shooting ----------------------------------------------------------------------------

class MultipleShooting:
    """G segments per run with their own initial (ω, q), one tensor and offset, and continuity defects.

    θ = [θ_I | (ω_g/ω_s (3), δθ_g (3)) for g in segments | b/σ_B (3)]. Defect between segment g's end
    and segment g+1's start: [2·vec(q_end⁻¹ ⊗ q_{g+1}) / σ_q, (ω_{g+1} − ω_end) / σ_ω].
    """

    def __init__(self, t_s: np.ndarray, b_meas: np.ndarray, b_samples: np.ndarray, action: KnownAction,
                 b_inertial: FieldFn, inertia: InertiaParam, bounds: np.ndarray, q_ref: np.ndarray,
                 sigma_b_T: float, *, fit_bias: bool = True, omega_scale: float = 0.01, h_max_s: float = 1.0,
                 fd_step: float = 1e-6, sigma_q_rad: float = 0.1, sigma_w_radps: float = 1e-3) -> None:
        self.t = np.asarray(t_s, float)
        self.b_meas = np.asarray(b_meas, float)
        self.inertia = inertia
        self.bounds = np.asarray(bounds, int)
        self.G = len(self.bounds) - 1
        self.q_ref = np.asarray(q_ref, float).copy()            # (R, G, 4)
        self.sigma = float(sigma_b_T)
        self.fit_bias = fit_bias
        self.omega_scale = omega_scale
        self.step = fd_step
        self.sigma_q = sigma_q_rad
        self.sigma_w = sigma_w_radps
        self.action, self.b_inertial, self.h_max_s = action, b_inertial, h_max_s
        n_used = self.bounds[-1] + 1
        self.seg = Segments.build(self.t[:n_used], self.bounds, action, b_inertial, h_max_s,
                                  b_samples=np.asarray(b_samples)[:n_used],
                                  unknown_intervals=inertia.unknown_intervals)
        # which local samples each segment predicts (its end belongs to the next segment)
        L = self.seg.b_local.shape[1]
        self.own = np.zeros((self.G, L), bool)
        for g in range(self.G):
            m = self.seg.n_local[g] - (0 if g == self.G - 1 else 1)
            self.own[g, :m] = True
        idx = np.zeros((self.G, L), int)
        for g in range(self.G):
            idx[g, :self.seg.n_local[g]] = np.arange(self.bounds[g], self.bounds[g + 1] + 1)
        self.sample_idx = idx

    @property
    def n_params(self) -> int:
        return self.inertia.n + 6 * self.G + (3 if self.fit_bias else 0)

    def subset(self, idx: np.ndarray) -> "MultipleShooting":
        """The same problem for the runs ``idx`` only (sharing the schedules)."""
        out = object.__new__(MultipleShooting)
        out.__dict__.update(self.__dict__)
        out.b_meas = self.b_meas[idx]
        out.q_ref = self.q_ref[idx].copy()
        out.inertia = self.inertia.subset(idx)
        return out

    def rechain(self, theta: np.ndarray, runs: np.ndarray, b_samples: np.ndarray) -> np.ndarray:
        """Re-chain the segments' attitudes: keep segment 0 and every segment's own motion (its body-frame
        attitude increment over the segment, from a nominal pass), take each next start from the
        previous end, re-tilted onto its own first sample. Returns θ with zero attitude parts (the
        attitudes go to ``q_ref``). Makes the angles about B, which a segment's own data cannot fix,
        consistent along the chain."""
        R = len(theta)
        n_I, G = self.inertia.n, self.G
        own = theta[:, n_I:n_I + 6 * G].reshape(R, G, 6)
        q_start = quat_mul(self.q_ref[runs], quat_exp(own[..., 3:]))           # (R, G, 4)
        th_I = np.repeat(theta[:, :n_I], G, axis=0)
        p = self.inertia.to_p(th_I, np.repeat(runs, G))
        bias = (np.repeat(theta[:, -3:], G, axis=0) * self.sigma if self.fit_bias else np.zeros((R * G, 3)))
        ps = Pass(self.seg, np.tile(np.arange(G), R), p.T, q_start.reshape(-1, 4).T,
                  (own[..., :3] * self.omega_scale).reshape(-1, 3).T, bias.T, u=self.inertia.to_moments(th_I))
        ps.advance()
        q_end = ps.y[:4].T.reshape(R, G, 4)
        dq = quat_mul(quat_conj(q_start), q_end)                              # body-frame increments
        new = q_start.copy()
        for r in range(R):
            for g in range(1, G):
                k = self.bounds[g]
                new[r, g] = retilt(quat_mul(new[r, g - 1], dq[r, g - 1]), self.b_meas[runs[r], k] -
                                   (theta[r, -3:] * self.sigma if self.fit_bias else 0.0), b_samples[k])
        self.q_ref[runs] = new
        out = theta.copy()
        o = out[:, n_I:n_I + 6 * G].reshape(R, G, 6)
        o[..., 3:] = 0.0
        out[:, n_I:n_I + 6 * G] = o.reshape(R, -1)
        return out

    def evaluate(self, thetas: np.ndarray, runs: np.ndarray):
        """Cost, data cost, normal matrix (:class:`BlockArrow`), gradient and dof of R runs."""
        return complete(evaluate_steps(self, thetas, runs, None))

    def begin(self, thetas: np.ndarray, runs: np.ndarray) -> tuple[Pass, tuple]:
        R, P = thetas.shape
        n_I, G = self.inertia.n, self.G
        k = 7 + n_I                                   # per segment: nominal, 6 own, n_I inertia
        nb = R * G * k
        th_I = np.repeat(thetas[:, None, :n_I], G * k, axis=1).reshape(nb, n_I)
        runs_b = np.repeat(runs, G * k)
        own = thetas[:, n_I:n_I + 6 * G].reshape(R, G, 6)
        st = np.repeat(own[:, :, None, :], k, axis=2)              # (R, G, k, 6)
        eye = np.eye(6) * self.step
        st[:, :, 1:7, :] += eye
        thI = th_I.reshape(R, G, k, n_I)
        thI[:, :, 7:, :] += np.eye(n_I) * self.step
        p = self.inertia.to_p(thI.reshape(nb, n_I), runs_b)
        u = self.inertia.to_moments(thI.reshape(nb, n_I))
        qref = np.repeat(self.q_ref[runs][:, :, None, :], k, axis=2).reshape(nb, 4)
        st = st.reshape(nb, 6)
        q0 = quat_mul(qref, quat_exp(st[:, 3:]))
        w0 = st[:, :3] * self.omega_scale
        if self.fit_bias:
            bias = np.repeat(thetas[:, n_I + 6 * G:], G * k, axis=0) * self.sigma
        else:
            bias = np.zeros((nb, 3))
        group = np.tile(np.repeat(np.arange(G), k), R)
        return Pass(self.seg, group, p.T, q0.T, w0.T, bias.T, u=u), (thetas, runs)

    def finish(self, ps: Pass, ctx: tuple):
        thetas, runs = ctx
        R, P = thetas.shape
        n_I, G = self.inertia.n, self.G
        k = 7 + n_I
        own = thetas[:, n_I:n_I + 6 * G].reshape(R, G, 6)
        L = self.seg.b_local.shape[1]
        pred = ps.pred.reshape(R, G, k, L, 3)
        yend = ps.y.T.reshape(R, G, k, 7)
        meas = self.b_meas[runs][:, self.sample_idx]                  # (R, G, L, 3)
        own_m = self.own[None, :, :, None]
        r = np.where(own_m, (pred[:, :, 0] - meas) / self.sigma, 0.0)          # (R, G, L, 3)
        Jd = np.where(own_m[:, :, None], (pred[:, :, 1:] - pred[:, :, :1]) / (self.step * self.sigma), 0.0)
        # defects
        dq = lambda qe, qs: 2.0 * quat_mul(quat_conj(qe), qs)[..., 1:] * np.sign(
            quat_mul(quat_conj(qe), qs)[..., :1] + 1e-300)
        q_start = quat_mul(self.q_ref[runs], quat_exp(own[..., 3:]))           # (R, G, 4)
        w_start = own[..., :3] * self.omega_scale
        qe, we = yend[..., :4], yend[..., 4:]                                  # (R, G, k, ·)
        dfe = np.concatenate([dq(qe[:, :-1], q_start[:, 1:, None, :]) / self.sigma_q,
                              (w_start[:, 1:, None, :] - we[:, :-1]) / self.sigma_w], axis=-1)  # (R, G-1, k, 6)
        d0 = dfe[:, :, 0]
        dJ_end = (dfe[:, :, 1:] - dfe[:, :, :1]) / self.step                   # (R, G-1, k-1, 6)
        # derivative of the defect wrt the next segment's own parameters (no integration needed)
        dJ_next = np.zeros((R, G - 1, 6, 6))
        for i in range(6):
            o = own[:, 1:].copy()
            o[..., i] += self.step
            qs = quat_mul(self.q_ref[runs][:, 1:], quat_exp(o[..., 3:]))
            d = np.concatenate([dq(qe[:, :-1, 0], qs) / self.sigma_q,
                                (o[..., :3] * self.omega_scale - we[:, :-1, 0]) / self.sigma_w], axis=-1)
            dJ_next[:, :, i, :] = (d - d0) / self.step
        data_cost = np.sum(r * r, axis=(1, 2, 3))
        cost = data_cost + np.sum(d0 * d0, axis=(1, 2))
        # normal equations in block form
        m = n_I + (3 if self.fit_bias else 0)
        Jr = Jd.reshape(R, G, k - 1, L * 3)                          # rows: own (6) | inertia (n_I)
        rr = r.reshape(R, G, L * 3)
        blk = np.einsum("rgim,rgjm->rgij", Jr, Jr)
        gb = np.einsum("rgim,rgm->rgi", Jr, rr)
        D = blk[:, :, :6, :6].copy()
        C = np.zeros((R, G, 6, m))
        C[:, :, :, :n_I] = blk[:, :, :6, 6:]
        Dm = np.zeros((R, m, m))
        Dm[:, :n_I, :n_I] = blk[:, :, 6:, 6:].sum(axis=1)
        gs = gb[:, :, :6].copy()
        gm = np.zeros((R, m))
        gm[:, :n_I] = gb[:, :, 6:].sum(axis=1)
        if self.fit_bias:
            # ∂r/∂(b/σ_B) = I on the owned samples (σ_B = σ): sums over each segment's samples
            Jx = Jr.reshape(R, G, k - 1, L, 3)
            ownf = self.own[None, :, None, :, None]
            cross = np.sum(Jx * ownf, axis=3)                           # (R, G, k−1, 3)
            C[:, :, :, n_I:] = cross[:, :, :6]
            Dm[:, :n_I, n_I:] = cross[:, :, 6:].sum(axis=1)
            Dm[:, n_I:, :n_I] = Dm[:, :n_I, n_I:].swapaxes(1, 2)
            Dm[:, n_I:, n_I:] = np.eye(3) * float(self.own.sum())
            gm[:, n_I:] = np.sum(r * self.own[None, :, :, None], axis=(1, 2))
        E = np.zeros((R, max(G - 1, 0), 6, 6))
        if G > 1:
            Dg = np.concatenate([dJ_end, dJ_next], axis=2)             # rows: own_g | inertia | own_{g+1}
            dblk = np.einsum("rgim,rgjm->rgij", Dg, Dg)
            dgb = np.einsum("rgim,rgm->rgi", Dg, d0)
            a, b_, c_ = slice(0, 6), slice(6, 6 + n_I), slice(6 + n_I, 12 + n_I)
            D[:, :-1] += dblk[:, :, a, a]
            D[:, 1:] += dblk[:, :, c_, c_]
            E[:] = dblk[:, :, a, c_]
            C[:, :-1, :, :n_I] += dblk[:, :, a, b_]
            C[:, 1:, :, :n_I] += dblk[:, :, c_, b_]
            Dm[:, :n_I, :n_I] += dblk[:, :, b_, b_].sum(axis=1)
            gs[:, :-1] += dgb[:, :, a]
            gs[:, 1:] += dgb[:, :, c_]
            gm[:, :n_I] += dgb[:, :, b_].sum(axis=1)
        P = self.n_params
        seg_idx = n_I + np.arange(6 * G).reshape(G, 6)
        glob_idx = np.concatenate([np.arange(n_I), np.arange(n_I + 6 * G, P)]).astype(int)
        g = np.zeros((R, P))
        g[:, seg_idx] = gs
        g[:, glob_idx] = gm
        bad = ~(np.isfinite(cost) & np.all(np.isfinite(D), axis=(1, 2, 3)) & np.all(np.isfinite(Dm), axis=(1, 2)))
        cost = np.where(bad, np.inf, cost)
        for arr in (D, E, C, Dm, g):
            arr[bad] = 0.0
        n_obs = int(self.own.sum()) * 3
        return cost, data_cost, BlockArrow(D, E, C, Dm, seg_idx, glob_idx), g, max(n_obs - P + 6 * (G - 1), 1)


# --- the identification pipeline --------------------------------------------------------------------

@dataclass
class FitResult:
    """Outcome of an output-error fit (one run)."""

    p: np.ndarray                 # (6,) tensor components, kg·m²
    cov_p: np.ndarray             # (6, 6)
    omega0_radps: np.ndarray
    q0: np.ndarray
    bias_T: np.ndarray
    chi2: float
    dof: int
    samples_used: int
    iterations: int
    converged: bool
    mode: str
    theta: np.ndarray
    cov_theta: np.ndarray
    unknown_intervals: tuple = ()              # (t0, t1) of the moments fitted as unknowns
    moment_sigma_Nm: tuple = ()                # their prior 1-σ (3,) each (inf: free)
    moments_Nm: np.ndarray | None = None       # (K, 3) their fitted values (in the tensor's scale)
    cov_moments: np.ndarray | None = None      # (3K, 3K)
    moment_unknown_samples: int = 0            # samples whose moment was unknown (NaN): fitted

    @property
    def s2(self) -> float:
        return self.chi2 / max(self.dof, 1)

    def estimate(self, method: str | None = None) -> inr.InertiaEstimate:
        return inr.InertiaEstimate(self.p.copy(), self.cov_p.copy(),
                                   method or f"output-error fit ({self.mode})", self.samples_used,
                                   self.mode in ("full", "shape", "scale"),
                                   extra={"chi2_per_dof": self.s2})


def turn_rate(t_s: np.ndarray, b_T: np.ndarray, k: int = 5) -> float:
    """Median rate [rad/s] at which the measured field direction turns, over k-sample steps (the part of
    ω across B; a lower bound of |ω|)."""
    b = np.asarray(b_T, float)
    t = np.asarray(t_s, float)
    k = max(1, min(k, len(t) - 1))
    u = b / np.linalg.norm(b, axis=1, keepdims=True)
    c = np.clip(np.sum(u[k:] * u[:-k], axis=1), -1.0, 1.0)
    return float(np.median(np.arccos(c) / (t[k:] - t[:-k])))


def segment_length(t_s: np.ndarray, b_T: np.ndarray, opts: "FitOptions") -> int:
    """Samples per segment: about ``opts.segment_angle_rad`` of turn, within [8, opts.segment_samples]."""
    dt = float(np.median(np.diff(t_s)))
    w = turn_rate(t_s, b_T)
    L = opts.segment_samples if w <= 0 else int(round(opts.segment_angle_rad / (w * dt)))
    return int(np.clip(L, 8, opts.segment_samples))


def initial_rates(t_s: np.ndarray, b_T: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """Rough ω per segment, from the samples alone (no dynamics).

    For a rigid turn in a fixed field the field direction b̂ runs on a circle about ω̂ (dB/dt = B × ω):
    the circle's plane normal (the least principal axis of the points b̂_k) is ±ω̂ and the signed turn
    of b̂ about it per second is −|ω|. Used when the segment's points spread along a clear arc;
    otherwise (a short arc, ω nearly along B) the mean Boer rate ω⊥ = (ΔB × B)/(Δt|B|²).
    """
    t = np.asarray(t_s, float)
    b = np.asarray(b_T, float)
    u = b / np.linalg.norm(b, axis=1, keepdims=True)
    db = np.diff(b, axis=0)
    boer = np.cross(db, b[1:]) / (np.diff(t)[:, None] * np.sum(b[1:] ** 2, axis=1, keepdims=True))
    out = np.zeros((len(bounds) - 1, 3))
    for g in range(len(bounds) - 1):
        a, e = bounds[g], max(bounds[g + 1], bounds[g] + 1)
        out[g] = boer[a:e].mean(axis=0)
        pts = u[a:e + 1]
        if len(pts) < 5:
            continue
        c = pts - pts.mean(axis=0)
        lam, vec = np.linalg.eigh(c.T @ c / len(pts))
        if not (lam[1] > 10.0 * lam[0] and lam[1] > 0.01):
            continue
        nrm = vec[:, 0]
        ctr = pts.mean(axis=0)
        rad = pts - ctr - np.outer(pts @ nrm - ctr @ nrm, nrm)
        ang = np.arctan2(np.einsum("ij,j->i", np.cross(rad[:-1], rad[1:]), nrm), np.sum(rad[:-1] * rad[1:], axis=1))
        rate = np.sum(ang) / (t[e] - t[a])
        out[g] = -rate * nrm
    return out


def chain_attitudes(t_s: np.ndarray, b_T: np.ndarray, b_samples: np.ndarray, bounds: np.ndarray,
                    omega: np.ndarray, angle0_rad: float = 0.0) -> np.ndarray:
    """Segment start attitudes: the first aligned with its sample (about-B angle ``angle0_rad``), each next
    one the previous turned by its rate over the segment and re-tilted onto its own sample."""
    G = len(bounds) - 1
    q = np.zeros((G, 4))
    q[0] = quat_aligning(b_T[bounds[0]], b_samples[bounds[0]], angle0_rad)
    for g in range(1, G):
        dt = t_s[bounds[g]] - t_s[bounds[g - 1]]
        qn = quat_mul(q[g - 1], quat_exp(omega[g - 1] * dt))
        q[g] = retilt(qn, b_T[bounds[g]], b_samples[bounds[g]])
    return q


@dataclass
class FitOptions:
    """Settings of :func:`identify` (defaults suit 1 Hz samples and rates of a few °/s)."""

    mode: str = "full"
    fit_bias: bool = True
    bias_sigma_T: float = 10e-6            # prior 1-σ of the offset
    inertia_prior_rel: float = 3.0         # prior 1-σ of each tensor component relative to the guess
    segment_samples: int = 30             # at most; fewer for a fast turn (segment_angle_rad per segment)
    segment_angle_rad: float = 1.2
    h_max_s: float = 1.0
    defect_schedule: tuple = ((1e3, 3e-3), (0.03, 3e-4), (3e-3, 3e-5))  # (σ_q rad, σ_ω rad/s)
    ms_iter: tuple = (40, 20, 20)            # LM iterations per stage
    ms_rtol: float = 1e-4
    ss_iter: int = 30
    ss_first_window: int = 150
    ss_growth: float = 1.6
    # (turn α deg, winding Ω deg/s) of the re-chained segments about their field direction, tried
    chain_candidates: tuple = ((0, 0), (90, 0), (180, 0), (270, 0), (0, -0.3), (0, 0.3))
    starts_about_b: int = 2                # single-shooting starts turned about B_I(t0) (best kept)
    omega_scale: float = 0.01


def identify(t_s: np.ndarray, b_meas: np.ndarray, b_inertial: FieldFn, action: KnownAction,
             sigma_b_T: float, p_guess: np.ndarray, opts: FitOptions | None = None, *,
             p_shape: np.ndarray | None = None, b_samples: np.ndarray | None = None,
             unknown_moments=(), log: Callable[[str], None] | None = None) -> list[FitResult]:
    """Identify the tensor (and the motion) from R runs of samples ``b_meas`` (R, n, 3) at ``t_s`` (n,).

    ``b_inertial`` the field model along the orbit, ``action`` the known moment/dipole, ``sigma_b_T``
    the per-axis noise, ``p_guess`` (6,) the starting tensor (also the mean of the weak prior),
    ``p_shape`` (R, 6) the fixed shape for mode ``"scale"``. ``unknown_moments``: (t0, t1) intervals on
    which a constant moment of unknown size acts (added to ``action``; fitted, started at zero, no
    prior) — with mode ``"shape"`` the whole record, pulses included, gives the tensor up to scale
    without relying on the size of the torque. Returns one :class:`FitResult` per run.
    """
    return complete(identify_steps(t_s, b_meas, b_inertial, action, sigma_b_T, p_guess, opts,
                                   p_shape=p_shape, b_samples=b_samples, unknown_moments=unknown_moments,
                                   log=log))


def identify_steps(t_s: np.ndarray, b_meas: np.ndarray, b_inertial: FieldFn, action: KnownAction,
                   sigma_b_T: float, p_guess: np.ndarray, opts: FitOptions | None = None, *,
                   p_shape: np.ndarray | None = None, b_samples: np.ndarray | None = None,
                   unknown_moments=(), log: Callable[[str], None] | None = None, chunk: int | None = None):
    """Generator form of :func:`identify`: yields every ``chunk`` integration steps; its value (the
    ``StopIteration`` value) is the list of results."""
    opts = opts or FitOptions()
    t = np.asarray(t_s, float)
    b_meas = np.asarray(b_meas, float)
    if b_meas.ndim == 2:
        b_meas = b_meas[None]
    R, n, _ = b_meas.shape
    if b_samples is None:
        b_samples = np.asarray(b_inertial(t), float).reshape(-1, 3)
    I_ref = float(np.mean(np.asarray(p_guess, float)[:3]))
    par = InertiaParam(opts.mode, I_ref, p_shape, *sm.merged(unknown_moments, action.unknown_intervals,
                                                             action.unknown_sigma_Nm))
    if any(b <= t[0] or a >= t[-1] for a, b in par.unknown_intervals):
        raise ValueError("an unknown-moment interval lies outside the record: nothing could fix its moment")
    bounds = segment_bounds(n, segment_length(t, b_meas[0], opts))
    G = len(bounds) - 1
    n_I = par.n
    th_I0 = np.array([par.from_p(p_guess, r) for r in range(R)])
    q_ref = np.zeros((R, G, 4))
    theta0 = np.zeros((R, n_I + 6 * G + (3 if opts.fit_bias else 0)))
    for r in range(R):
        w_g = initial_rates(t, b_meas[r], bounds)
        q_ref[r] = chain_attitudes(t, b_meas[r], b_samples, bounds, w_g)
        theta0[r, :n_I] = th_I0[r]
        seg = np.zeros((G, 6))
        seg[:, :3] = w_g / opts.omega_scale
        theta0[r, n_I:n_I + 6 * G] = seg.ravel()
    ms = MultipleShooting(t, b_meas, b_samples, action, b_inertial, par, bounds, q_ref, sigma_b_T,
                          fit_bias=opts.fit_bias, omega_scale=opts.omega_scale, h_max_s=opts.h_max_s)
    prior = _prior(ms.n_params, n_I, th_I0[0], opts, sigma_b_T, par)
    runs = LMRuns(theta0)
    # stage 1: segments fitted to their own arcs, tied only loosely by the rate, then re-chained
    ms.sigma_q, ms.sigma_w = opts.defect_schedule[0]
    yield from lm_steps(ms, runs, prior, opts.ms_iter[0], rtol=opts.ms_rtol, chunk=chunk)
    runs.theta = ms.rechain(runs.theta, np.arange(R), b_samples)
    if chunk is not None:
        yield
    if log:
        log(f"multiple shooting, {G} segments, loose: χ²/(3n) "
            + " ".join(f"{c / (3 * n):.3f}" for c in runs.data_cost[:8]))
    # The re-chained chain is known only up to turns of its segments about their own field direction,
    # which one sample per segment cannot see: a common turn α (fixed only by the field's motion along
    # the orbit) and a winding Ω·t (each segment's rate along B is its least certain part; the
    # dynamics tell windings apart). A few candidates go through the tightening stages; the best of
    # each run is kept.
    cand = np.radians(np.asarray(opts.chain_candidates, float))
    W = len(cand)
    msw, thw = _turned(ms, runs.theta, np.broadcast_to(cand, (R, W, 2)), t, b_samples,
                       np.repeat(np.arange(R), W))
    if chunk is not None:
        yield
    wruns = LMRuns(thw)
    wrun = np.repeat(np.arange(R), W)                    # run of each candidate
    for stage in range(1, len(opts.defect_schedule)):
        msw.sigma_q, msw.sigma_w = opts.defect_schedule[stage]
        yield from lm_steps(msw, wruns, prior, opts.ms_iter[min(stage, len(opts.ms_iter) - 1)],
                            rtol=opts.ms_rtol, chunk=chunk)
        if log:
            log(f"multiple shooting σ_q={msw.sigma_q:g} rad σ_ω={msw.sigma_w:g} rad/s, {len(wrun)} chains: "
                "χ²/(3n) " + " ".join(f"{c / (3 * n):.3f}" for c in wruns.data_cost[:8]))
        if stage < len(opts.defect_schedule) - 1:
            # candidates that reached the same chain as a better one, or a clearly worse one, stop here
            keep = _distinct_best(wrun, wruns.theta[:, :n_I], wruns.cost, tol=2e-3, same_cost=0.5)
            msw, wrun = msw.subset(keep), wrun[keep]
            sub = LMRuns(wruns.theta[keep].copy())
            sub.cost, sub.data_cost = wruns.cost[keep], wruns.data_cost[keep]
            wruns = sub
    wc = np.where(np.isfinite(wruns.cost), wruns.cost, np.inf)
    pick = np.array([np.flatnonzero(wrun == r)[np.argmin(wc[wrun == r])] for r in range(R)])
    best_theta = wruns.theta[pick]
    best_q = msw.q_ref[pick]
    # The chain is fixed up to a rotation about B_I(t0), to which the defects are blind: single shooting
    # from segment 0 turned by each of S angles about B_I(t0) (virtual runs), over windows growing to
    # the end; the best of each run is kept.
    S = max(1, opts.starts_about_b)
    V = R * S
    vrun = np.repeat(np.arange(R), S)
    bv = b_meas[vrun]
    p_shape_v = None if p_shape is None else np.asarray(p_shape, float)[vrun]
    q0 = quat_mul(best_q[:, 0], quat_exp(best_theta[:, n_I + 3:n_I + 6]))[vrun]
    bI0 = b_samples[0] / np.linalg.norm(b_samples[0])
    q0 = quat_mul(quat_exp(np.outer(2 * np.pi * (np.arange(V) % S) / S, bI0)), q0)
    theta = np.zeros((V, n_I + 6 + (3 if opts.fit_bias else 0)))
    theta[:, :n_I] = best_theta[vrun, :n_I]
    theta[:, n_I:n_I + 3] = best_theta[vrun, n_I:n_I + 3]
    if opts.fit_bias:
        theta[:, n_I + 6:] = best_theta[vrun, -3:]
    alive = np.arange(V)
    windows = _ss_windows(n, opts.ss_first_window, opts.ss_growth)
    for wi, nw in enumerate(windows):
        pv = InertiaParam(opts.mode, I_ref, None if p_shape_v is None else p_shape_v[alive], par.unknown_intervals,
                          par.moment_sigma_Nm)
        ss = SingleShooting(t, bv[alive], b_samples, action, b_inertial, pv, q0[alive], sigma_b_T, n=nw,
                            fit_bias=opts.fit_bias, omega_scale=opts.omega_scale, h_max_s=opts.h_max_s)
        prior = _prior(ss.n_params, n_I, th_I0[0], opts, sigma_b_T, pv)
        # the tensor stays at the multiple-shooting value until the whole record is fitted: a prefix
        # alone determines it less well and would pull it off
        frozen = np.arange(ss.n_params) < n_I if wi < len(windows) - 1 else None
        sruns = LMRuns(theta[alive].copy())
        yield from lm_steps(ss, sruns, prior, opts.ss_iter, frozen=frozen, chunk=chunk)
        theta[alive] = sruns.theta
        if log:
            log(f"single shooting, {nw} samples, {alive.size} starts: χ²/dof "
                + " ".join(f"{c / sruns.dof:.3f}" for c in sruns.data_cost[:8]))
        if wi < len(windows) - 1:
            phys = np.delete(theta[alive], np.arange(n_I + 3, n_I + 6), axis=1)
            alive = alive[_distinct_best(vrun[alive], phys, sruns.cost)]
    allres = results(ss, sruns, prior)
    for res in allres:
        res.moment_unknown_samples = sm.samples_in(t, action.unknown_intervals)
    out = []
    for r in range(R):
        cand = [allres[j] for j in np.flatnonzero(vrun[alive] == r)]
        costs = np.array([c.chi2 + prior.cost(c.theta) for c in cand])
        out.append(cand[int(np.argmin(np.where(np.isfinite(costs), costs, np.inf)))])
    return out


def _distinct_best(run_of: np.ndarray, theta: np.ndarray, cost: np.ndarray, tol: float = 1e-3,
                   margin: float = 100.0, same_cost: float = 0.1) -> np.ndarray:
    """Indices to keep: per run, drop starts that reached the same point as a better one (``theta``
    within ``tol`` in scaled units and cost within ``same_cost``) and starts whose cost exceeds the
    run's best by more than ``margin`` + 50 %."""
    keep = []
    for r in np.unique(run_of):
        idx = np.flatnonzero(run_of == r)
        order = idx[np.argsort(np.where(np.isfinite(cost[idx]), cost[idx], np.inf))]
        best = cost[order[0]]
        kept: list[int] = []
        for i in order:
            if not np.isfinite(cost[i]) or cost[i] > best + margin + 0.5 * abs(best):
                continue
            if any(np.max(np.abs(theta[i] - theta[j])) < tol and abs(cost[i] - cost[j]) < same_cost
                   for j in kept):
                continue
            kept.append(i)
        keep.extend(kept or [order[0]])
    return np.array(sorted(keep))


def _turned(ms: "MultipleShooting", theta: np.ndarray, cand: np.ndarray, t: np.ndarray,
            b_samples: np.ndarray, vrun: np.ndarray) -> tuple["MultipleShooting", np.ndarray]:
    """Copies of a multiple-shooting problem, one per (run, candidate): candidate (α, Ω) turns every
    segment's attitude about its own field direction B̂_I(t_g) by α + Ω·(t_g − t_mid) and adds Ω B̂
    (body axes) to its rate — what one sample per segment cannot see: α turns the chain about the
    field, Ω winds it.
    ``cand`` (R, C, 2) in rad and rad/s; virtual run v = r·C + c."""
    R, C, _ = cand.shape
    n_I, G = ms.inertia.n, ms.G
    a = b_samples[ms.bounds[:-1]]
    a = a / np.linalg.norm(a, axis=1, keepdims=True)              # B̂_I at each segment start
    tg = t[ms.bounds[:-1]] - t[ms.bounds[G // 2]]
    q_new = np.zeros((R * C, G, 4))
    th = np.repeat(theta, C, axis=0)
    for r in range(R):
        own = theta[r, n_I:n_I + 6 * G].reshape(G, 6)
        qg = quat_mul(ms.q_ref[r], quat_exp(own[:, 3:]))
        for j in range(C):
            alpha, om = cand[r, j]
            v = r * C + j
            q_new[v] = quat_mul(quat_exp((alpha + om * tg)[:, None] * a), qg)
            o = own.copy()
            o[:, :3] += om * np.einsum("gij,gj->gi", _dcm(q_new[v]).swapaxes(1, 2), a) / ms.omega_scale
            o[:, 3:] = 0.0
            th[v, n_I:n_I + 6 * G] = o.ravel()
    par = ms.inertia
    parw = par.subset(vrun)
    msw = MultipleShooting(ms.t, ms.b_meas[vrun], b_samples, ms.action, ms.b_inertial, parw, ms.bounds, q_new,
                           ms.sigma, fit_bias=ms.fit_bias, omega_scale=ms.omega_scale, h_max_s=ms.h_max_s,
                           fd_step=ms.step, sigma_q_rad=ms.sigma_q, sigma_w_radps=ms.sigma_w)
    return msw, th


def _ss_windows(n: int, first: int, growth: float) -> list[int]:
    out = [min(n, max(first, 10))]
    while out[-1] < n:
        out.append(min(n, int(math.ceil(out[-1] * growth))))
    return out


def _prior(P: int, n_I: int, th_I0: np.ndarray, opts: FitOptions, sigma_b_T: float,
           par: InertiaParam) -> Prior:
    mean = np.zeros(P)
    sig = np.full(P, np.inf)
    mean[:n_I] = th_I0
    rel = opts.inertia_prior_rel
    nt = par.n_tensor
    sig[:nt] = rel if par.mode != "scale" else rel * max(abs(th_I0[0]), 1.0)
    for k, s in enumerate(par.moment_sigma_Nm):                  # the unknown moments: free unless given
        sig[nt + 3 * k:nt + 3 * k + 3] = np.asarray(s, float) / par.moment_scale_Nm
    if opts.fit_bias:
        sig[-3:] = opts.bias_sigma_T / sigma_b_T
    return Prior(mean, sig)


def results(ss: SingleShooting, runs: LMRuns, prior: Prior | None) -> list[FitResult]:
    """FitResults of single-shooting runs: tensor, covariance s²(JᵀJ + prior)⁻¹ with s² = χ²/dof."""
    par = ss.inertia
    n_I = par.n
    R, P = runs.theta.shape
    w2 = prior.w ** 2 if prior is not None else np.zeros(P)
    inv = runs.A.inverse(np.broadcast_to(w2, (R, P)))
    out = []
    for r in range(R):
        s2 = runs.data_cost[r] / max(runs.dof, 1)
        cov = s2 * inv[r]
        T, c = par.affine(r)
        p = T @ runs.theta[r, :n_I] + c
        pp, q0, w0, bias = ss.unpack(runs.theta[r:r + 1], np.array([r]))
        mom, cov_m = par.moments_of(runs.theta[r, :n_I], cov[:n_I, :n_I]) if par.n_moments else (None, None)
        out.append(FitResult(p, T @ cov[:n_I, :n_I] @ T.T, w0[0], q0[0], bias[0], float(runs.data_cost[r]),
                             runs.dof, ss.n, int(runs.iterations[r]), bool(runs.converged[r]), par.mode,
                             runs.theta[r].copy(), cov, par.unknown_intervals, par.moment_sigma_Nm, mom, cov_m))
    return out


def single_shooting_for(t_s: np.ndarray, b_meas: np.ndarray, b_inertial: FieldFn, action: KnownAction,
                        sigma_b_T: float, result: FitResult, opts: FitOptions | None = None, *,
                        n: int | None = None, b_samples: np.ndarray | None = None,
                        p_shape: np.ndarray | None = None) -> tuple[SingleShooting, np.ndarray]:
    """The single-shooting problem of one run (``b_meas`` (n, 3)) and the θ of ``result`` in it."""
    opts = opts or FitOptions(mode=result.mode)
    t = np.asarray(t_s, float)
    if b_samples is None:
        b_samples = np.asarray(b_inertial(t), float).reshape(-1, 3)
    p_ref = result.p if p_shape is None else np.asarray(p_shape, float)
    par = InertiaParam(result.mode, float(np.mean(p_ref[:3])) if result.mode != "shape" else float(result.p[0]),
                       None if p_shape is None else np.atleast_2d(p_shape), result.unknown_intervals,
                       result.moment_sigma_Nm)
    ss = SingleShooting(t, np.asarray(b_meas, float)[None], b_samples, action, b_inertial, par,
                        result.q0[None], sigma_b_T, n=n, fit_bias=opts.fit_bias, omega_scale=opts.omega_scale,
                        h_max_s=opts.h_max_s)
    theta = np.zeros(ss.n_params)
    theta[:par.n] = par.from_p(result.p, moments_Nm=result.moments_Nm)
    theta[par.n:par.n + 3] = result.omega0_radps / opts.omega_scale
    if opts.fit_bias:
        theta[par.n + 6:] = result.bias_T / sigma_b_T
    return ss, theta


def cramer_rao(t_s: np.ndarray, b_inertial: FieldFn, action: KnownAction, sigma_b_T: float, p: np.ndarray,
               q0: np.ndarray, omega0_radps: np.ndarray, opts: FitOptions | None = None, *,
               unknown_moments=(), moments_Nm: np.ndarray | None = None,
               b_samples: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Cramér–Rao bound of the fit: the covariance (F + prior)⁻¹ of (p, unknown moments) that an efficient
    estimator reaches, F = JᵀJ/σ_B² the Fisher information of white noise σ_B per axis, J the Jacobian
    of the predicted samples at the given parameters (the truth, in a simulation) — tensor ``p`` (for
    ``opts.mode`` "shape" its scale is the one of ``p``), start state (``q0``, ``omega0_radps``) at
    ``t_s[0]``, zero offset, ``moments_Nm`` (K, 3) on ``unknown_moments``. Returns (cov_p (6, 6),
    cov of the moments (3K, 3K))."""
    opts = opts or FitOptions()
    t = np.asarray(t_s, float)
    if b_samples is None:
        b_samples = np.asarray(b_inertial(t), float).reshape(-1, 3)
    p = np.asarray(p, float)
    I_ref = float(p[0]) if opts.mode in ("shape", "shape_diag") else float(np.mean(p[:3]))
    par = InertiaParam(opts.mode, I_ref, p[None] if opts.mode == "scale" else None,
                       *sm.merged(unknown_moments, action.unknown_intervals, action.unknown_sigma_Nm))
    ss = SingleShooting(t, np.zeros((1, len(t), 3)), b_samples, action, b_inertial, par,
                        np.asarray(q0, float)[None], sigma_b_T, fit_bias=opts.fit_bias,
                        omega_scale=opts.omega_scale, h_max_s=opts.h_max_s)
    theta = np.zeros(ss.n_params)
    theta[:par.n] = par.from_p(p, moments_Nm=moments_Nm)
    theta[par.n:par.n + 3] = np.asarray(omega0_radps, float) / opts.omega_scale
    _, _, A, _, _ = ss.evaluate(theta[None], np.zeros(1, int))
    prior = _prior(ss.n_params, par.n, theta[:par.n], opts, sigma_b_T, par)
    cov = A.inverse((prior.w ** 2)[None])[0]
    T, _ = par.affine()
    nI, nt = par.n, par.n_tensor
    s = par.moment_scale_Nm
    return T @ cov[:nI, :nI] @ T.T, cov[nt:nI, nt:nI] * s * s


def trajectory(t_s: np.ndarray, b_meas: np.ndarray, b_inertial: FieldFn, action: KnownAction,
               sigma_b_T: float, result: FitResult, opts: FitOptions | None = None, *,
               p_shape: np.ndarray | None = None) -> dict:
    """The fitted motion at the samples: ``b_body_T`` (predicted field), ``q``, ``omega_radps``."""
    ss, theta = single_shooting_for(t_s, b_meas, b_inertial, action, sigma_b_T, result, opts, p_shape=p_shape)
    return ss.trajectory(theta)


def propagate(q0: np.ndarray, omega0_radps: np.ndarray, p: np.ndarray, t0_s: float, times_s: np.ndarray,
              action: KnownAction, b_inertial: FieldFn | None = None, h_max_s: float = 0.1) -> dict:
    """Integrate the model from (q₀, ω₀) at t₀ to ``times_s`` (increasing, > t₀): ``q``, ``omega_radps``."""
    times = np.asarray(times_s, float)
    t = np.concatenate([[t0_s], times])
    bf = b_inertial if b_inertial is not None else (lambda tt: np.tile([1e-9, 0.0, 0.0], (len(tt), 1)))
    seg = Segments.build(t, [0, len(t) - 1], action, bf, h_max_s)
    ps = Pass(seg, np.zeros(1, int), np.asarray(p, float)[:, None], np.asarray(q0, float)[:, None],
              np.asarray(omega0_radps, float)[:, None], np.zeros((3, 1)), keep_states=True)
    ps.advance()
    st = ps.states[0, 1:]
    return {"q": st[:, :4], "omega_radps": st[:, 4:]}


def prefix_fits(t_s: np.ndarray, b_meas: np.ndarray, b_inertial: FieldFn, action: KnownAction,
                sigma_b_T: float, final: FitResult, lengths: list[int], p_guess: np.ndarray,
                opts: FitOptions | None = None, *, b_samples: np.ndarray | None = None) -> list[FitResult]:
    """The running estimate: the fit of the first n samples for each n in ``lengths`` (one run,
    ``b_meas`` (n, 3)), each warm-started from the fit of the whole record, which puts it in the right
    basin. A short prefix (before any torque) leaves the scale to the weak prior: its band is wide."""
    opts = opts or FitOptions(mode=final.mode)
    t = np.asarray(t_s, float)
    if b_samples is None:
        b_samples = np.asarray(b_inertial(t), float).reshape(-1, 3)
    out = []
    for n in lengths:
        ss, theta = single_shooting_for(t, b_meas, b_inertial, action, sigma_b_T, final, opts, n=int(n),
                                        b_samples=b_samples)
        th_I0 = ss.inertia.from_p(np.asarray(p_guess, float))
        prior = _prior(ss.n_params, ss.inertia.n, th_I0, opts, sigma_b_T, ss.inertia)
        runs = lm(ss, LMRuns(theta[None].copy()), prior, opts.ss_iter)
        out.append(results(ss, runs, prior)[0])
    return out
