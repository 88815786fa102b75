"""Propagation of the model for a batch of trajectories.

RK4 between the sample times and the switch times of the known action, vectorised over a batch of
trajectories — every segment of every Monte-Carlo run, nominal and one forward-difference perturbation
per parameter (the Jacobian). A :class:`Pass` is resumable: the flight software advances it a few
steps per loop tick. Quaternions are laid out components first here, (4, nb), as the batch is.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .model import FieldFn, KnownAction

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
    # (T, G, 3, 3) at the stages: gravity vectors and (with `drag`) scaled velocities, `KnownAction.environment_vectors`
    g_stage: np.ndarray | None = None
    v_stage: np.ndarray | None = None
    drag: object = None                 # the spacecraft model whose drag acts (`KnownAction.drag`), or None

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
        g_stage = v_stage = None
        if action.orbit_position_m is not None:
            on = H > 0
            ts = np.stack([T0[on], mid[on], T0[on] + H[on]], axis=1)
            g, v = action.environment_vectors(ts.ravel())
            g_stage = np.zeros((T, G, 3, 3))
            g_stage[on] = g.reshape(-1, 3, 3)
            if v is not None:
                v_stage = np.zeros((T, G, 3, 3))
                v_stage[on] = v.reshape(-1, 3, 3)
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
        return Segments(t, bounds, H, moment, dipole, magnetic, b_stage, REC, b_local, n_local, steps, unknown,
                        g_stage, v_stage, action.drag if v_stage is not None else None)


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
    """R(q)ᵀ v for unit quaternions q (4, nb) and v (3,) or (3, nb) → (3, nb).

    The measurement model of every RK4 step, written out rather than as
    ``rotations.quat_to_dcm(q).T @ v``: no (nb, 3, 3) matrices per step."""
    w, x, y, z = q
    v0, v1, v2 = v[0], v[1], v[2]
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    return np.array([
        (1 - 2 * (yy + zz)) * v0 + 2 * (xy + wz) * v1 + 2 * (xz - wy) * v2,
        2 * (xy - wz) * v0 + (1 - 2 * (xx + zz)) * v1 + 2 * (yz + wx) * v2,
        2 * (xz + wy) * v0 + 2 * (yz - wx) * v1 + (1 - 2 * (xx + yy)) * v2,
    ])


def _drag_moment(q: np.ndarray, v_I: np.ndarray, d) -> np.ndarray:
    """r_cp × F of the drag of the spacecraft model `d` (`orbital_attitude.SpacecraftModel`) for attitudes
    q (4, nb) at the velocity v_I (3, nb) → (3, nb)."""
    v = body_from_inertial(q, v_I)
    speed = np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    n = d.sail_normal_body
    # a padded step (h = 0) has no velocity: its moment is zero, never 0/0
    area = d.sail_area_m2 * np.abs(n[0] * v[0] + n[1] * v[1] + n[2] * v[2]) / np.where(speed > 0, speed, 1.0) \
        + d.body_area_m2
    f = (-0.5 * d.density_kgm3 * d.drag_coefficient) * area * speed * v      # −½ρ|v|²C_d S v̂
    rx, ry, rz = d.cp_offset_m
    return np.array([ry * f[2] - rz * f[1], rz * f[0] - rx * f[2], rx * f[1] - ry * f[0]])


def _deriv(y: np.ndarray, J: np.ndarray, K: np.ndarray, M, dip, b_I, g_I=None, v_I=None, drag=None) -> np.ndarray:
    """d/dt of y = [q (4), ω (3)] (7, nb); J, K = J⁻¹ as (6, nb) components; M (3,) or (3, nb); `g_I` the
    gravity vector (3, nb) in inertial axes (None: no gravity gradient); `v_I` the orbital velocity (3, nb)
    with `drag` (the spacecraft model; None: no aerodynamic moment)."""
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
    if g_I is not None:   # 3μ/r³ r̂ × (J r̂) = g × (J g)
        gx, gy, gz = body_from_inertial(y[:4], g_I)
        G1 = J11 * gx + J12 * gy + J13 * gz
        G2 = J12 * gx + J22 * gy + J23 * gz
        G3 = J13 * gx + J23 * gy + J33 * gz
        Mx = Mx + gy * G3 - gz * G2
        My = My + gz * G1 - gx * G3
        Mz = Mz + gx * G2 - gy * G1
    if drag is not None:
        ax, ay, az = _drag_moment(y[:4], v_I, drag)
        Mx, My, Mz = Mx + ax, My + ay, Mz + az
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
                ga = gm = gb = va = vm = vb = None
                if s.g_stage is not None:
                    gs = s.g_stage[i, g]                                     # (nb, 3, 3)
                    ga, gm, gb = gs[:, 0].T, gs[:, 1].T, gs[:, 2].T
                if s.drag is not None:
                    vs = s.v_stage[i, g]
                    va, vm, vb = vs[:, 0].T, vs[:, 1].T, vs[:, 2].T
                dr = s.drag
                if s.magnetic[i]:
                    dip = s.dipole[i, g].T
                    bs = s.b_stage[i, g]                                     # (nb, 3, 3)
                    k1 = _deriv(y, J, K, M, dip, bs[:, 0].T, ga, va, dr)
                    k2 = _deriv(y + (0.5 * h) * k1, J, K, M, dip, bs[:, 1].T, gm, vm, dr)
                    k3 = _deriv(y + (0.5 * h) * k2, J, K, M, dip, bs[:, 1].T, gm, vm, dr)
                    k4 = _deriv(y + h * k3, J, K, M, dip, bs[:, 2].T, gb, vb, dr)
                else:
                    k1 = _deriv(y, J, K, M, None, None, ga, va, dr)
                    k2 = _deriv(y + (0.5 * h) * k1, J, K, M, None, None, gm, vm, dr)
                    k3 = _deriv(y + (0.5 * h) * k2, J, K, M, None, None, gm, vm, dr)
                    k4 = _deriv(y + h * k3, J, K, M, None, None, gb, vb, dr)
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
