"""The de-orbit kit's magnets at the magnetometer, modelled on board and taken out of every sample.

Each magnet is a point dipole at ``position_m`` (body axes, from the magnetometer to the magnet's
centre) with the moment ``moment_Am2`` along its home axis ``a`` turned about its shaft ``u`` by the
rotor angle φ (the stepper's counted position, 1.8° a step): m = p (cos φ a + sin φ u × a) for a ⟂ u.
Its field at the sensor (r = −position, r̂ = r/|r|) is linear in the moment::

    K(φ) = cos φ F_a + sin φ F_b,   F_a = μ0/(4π|r|³) (3 (p a·r̂) r̂ − p a),  F_b the same for p u × a

and the capsule screens it: a closed capsule leaks ``leakage`` of it (1-2 %), an open one lets all of
it out. So a channel at rest adds s (cos φ F_a + sin φ F_b) with s = leakage (CLOSED) or 1 (OPEN).
The state comes from the kit's own drivers (`fsw.drivers.stepper`, `fsw.drivers.capsule` through the
sequencer's channels), polled every loop tick (:meth:`KitFieldModel.poll`).

Motion: while a shutter opens or closes, a capsule is in FAULT, or a magnet turns or homes, the
screening or the angle is not known well enough: the samples taken then (with one loop period of
margin on either side: the chip's sample time and the drivers' state are a tick apart) are *flagged*
(:meth:`KitFieldModel.field_at` returns ``skip``) and the flight loop keeps them from the host
calibration, the estimators and the applications; they are still sent and stored as the sensor's own.

Calibration on orbit (:meth:`KitFieldModel.record` with the accepted samples): every motion of a
channel between two rest states A → B is a known change of its field, Δ = c_a F_a + c_b F_b with
c_a = s_B cos φ_B − s_A cos φ_A (c_b likewise with sin). The body turns meanwhile, so the step is
estimated against the field's motion: one least-squares fit of the raw samples, compensated with the
current model, on both sides of the motion (up to ``window_s`` each, cut at the neighbouring steps of an
open field before and any motion after; halved while the residual exceeds ``misfit`` times the noise)
to the Earth's field turning with the body plus a step at the motion (:func:`rotating_step_fit`)::

    y(τ) = exp(−[θ(τ)]×) (B0 + B1 τ) + h + d·[τ > 0],   θ(τ) = Σ_k a_k τ^k (k = 1 … ``degree``)

τ the time from the motion's middle in units of the window, y the samples with the host's calibration
applied (``host``: the flight loop's, when it has a good one; the step is mapped back to the sensor's
axes through its soft iron), h what stays fixed in the body (the host's iron the calibration left, the
kit's model error before the motion). The rotation keeps the Earth's field's magnitude (only B1, its
change along the orbit, prior 1-σ ``field_rate_T_per_s``, changes it), so the fit has 3·degree + 12
unknowns shared by the three axes where a polynomial per axis has 12 + 3 that follow a turning field
only so far and are biased by what they miss: on a free body tumbling at 4 and 8 °/s the step's RMS
error is 10 and 25 % below a cubic's (tests/fsw/test_kit_field.py), and its σ covers it; on the
mission's seed 5 (4.1 °/s) the identification's one opening is fitted 0.9 µT off, against 3.8 µT.
The fitted step d is what the model missed. Motions of several channels that overlap (the controller
closes one capsule as it opens the other) are one step, so the channels' F_a are estimated jointly:
x = (F_a,pitch, F_a,yaw) with its covariance P, the observation d = H (x_true − x) with H = (c_a,pitch I, c_a,yaw I)
and R the covariance of d (the fit's, scaled by its χ² per degree of freedom when above 1); a
Kalman update of a constant, prior: the design value with ``prior_frac`` of |F_a| per axis. A step is
not taken in when it is

- weak: every |c_a| < 0.5 (a turn while closed moves only the 1-2 % leakage) — ``weak_steps``;
- ill-conditioned: too few samples on a side (the next motion came too soon, the first step of a
  run), a σ of d over |c_a| above ``max_sigma_frac`` of |F_a|, or left waiting behind ``max_jobs``
  others — counted ``ill_conditioned``;
- an outlier: a χ² of d against H P Hᵀ + R above ``chi2_max`` (3 degrees of freedom, 99.9 %), or an
  updated |F_a| outside [0.5, 1.5] of the design's — counted ``outliers``;

the last good calibration stays applied. The channel's scale k = F_a·F_a,design / |F_a,design|² (the
moment as the sensor sees it, with its 1-σ) scales F_b, which the polarities the controller uses
(φ = 0°, 180°) do not observe. The leakage stays the design's (an error of 0.5 % of it is 0.5 µT at
0.3 m). DEBRIS_KIT_FIELD (one per channel) reports the scale, its σ, the latest step's innovation and
fit residual and the counters.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from fsw.drivers.capsule import CapsuleState
from fsw.drivers.stepper import STEPS_PER_TURN, MagnetState
from fsw.estimation.euler_fit.solver import complete
from fsw.estimation.rotations import quat_exp, quat_to_dcm, skew

MU0_4PI = 1e-7  # μ0 / 4π [T·m/A]
#: χ² of a 3-vector at 99.9 %
CHI2_3_999 = 16.27


@dataclass(frozen=True)
class MagnetGeometry:
    """One channel's magnet as designed: where it is (from the magnetometer, body axes), its moment,
    its axis at home (polarity +1), the shaft it turns about, its capsule's leakage when closed."""

    position_m: tuple[float, float, float]
    home_axis: tuple[float, float, float]
    moment_Am2: float = 15.0
    shaft_axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    leakage: float = 0.015

    def __post_init__(self) -> None:
        p, a, u = (np.asarray(v, dtype=float) for v in (self.position_m, self.home_axis, self.shaft_axis))
        if not (p.shape == a.shape == u.shape == (3,) and np.all(np.isfinite(np.concatenate((p, a, u))))):
            raise ValueError("magnet position, home axis and shaft axis must be finite 3-vectors")
        if np.linalg.norm(p) < 0.01:
            raise ValueError(f"a magnet must sit at least 1 cm from the sensor, got {self.position_m}")
        if not (abs(np.linalg.norm(a) - 1) < 1e-6 and abs(np.linalg.norm(u) - 1) < 1e-6 and abs(a @ u) < 1e-6):
            raise ValueError("home axis and shaft axis must be orthogonal unit vectors")
        if not (math.isfinite(self.moment_Am2) and self.moment_Am2 > 0 and 0.0 <= self.leakage <= 1.0):
            raise ValueError("moment must be > 0 A·m², leakage within [0, 1]")


#: the kit as built (hil.deorbit_kit): pitch magnet along z at +0.3 m y, yaw magnet along y at −0.3 m z,
#: both turned about body x
DESIGN = (MagnetGeometry((0.0, 0.3, 0.0), (0.0, 0.0, 1.0)), MagnetGeometry((0.0, 0.0, -0.3), (0.0, 1.0, 0.0)))


def dipole_field_T(m_Am2: np.ndarray, position_m: np.ndarray) -> np.ndarray:
    """Field [T] at the sensor of a point dipole `m_Am2` at `position_m` from the sensor."""
    r = -np.asarray(position_m, dtype=float)
    d = float(np.linalg.norm(r))
    rh = r / d
    m = np.asarray(m_Am2, dtype=float)
    return MU0_4PI / d**3 * (3.0 * float(m @ rh) * rh - m)


#: prior 1-σ of the rotation polynomial's coefficients [rad per window^k]: the first a rate of up to
#: ~20 rad a window (a weak bound, it keeps the rotation about the field regular on a slow body), the
#: others the rate's change
ROTATION_PRIOR_RAD = (20.0, 0.5)
#: prior 1-σ of what stays fixed in the body [T]: the host's hard iron before its calibration (a weak
#: bound; on a slow body it keeps B0 and h apart)
OFFSET_PRIOR_T = 50e-6


def rotating_step_fit(tau: np.ndarray, after: np.ndarray, y_T: np.ndarray, sigma_T: float,
                      b1_sigma_T: float, degree: int = 3, iterations: int = 12
                      ) -> tuple[np.ndarray, np.ndarray, float] | None:
    """The step `d` [T] in samples `y_T` (n, 3) at times `tau` (n,) (−1 … 1, 0 at the motion; `after`:
    the samples after it) of the Earth's field turning with the body (the module's model), by
    Levenberg-Marquardt from the rate the samples' own derivatives give (ẏ = y × θ̇ on each side).
    Returns (d, its covariance [T²] — the fit's, scaled by the residual's χ² per degree of freedom when
    above 1 —, the residual RMS per axis [T], at least `sigma_T`), or None (too few samples, singular).
    At once: :func:`rotating_step_fit_steps` is the same fit an iteration at a time."""
    return complete(rotating_step_fit_steps(tau, after, y_T, sigma_T, b1_sigma_T, degree, iterations))


def rotating_step_fit_steps(tau, after, y_T, sigma_T, b1_sigma_T, degree=3, iterations=12):
    """:func:`rotating_step_fit` as a generator: it yields after each iteration (~1-3 ms at 320 samples)
    and returns the fit, so that the flight loop spreads it over its ticks."""
    n, na = len(tau), 3 * degree
    nq = na + 12  # θ's coefficients, B0, B1, h, d
    if n < nq or np.count_nonzero(after) < 4 or np.count_nonzero(~after) < 4:
        return None
    # the rate at the start: ẏ = y × θ̇ = [y]× θ̇ from a cubic per axis on each side
    rows, rhs = [], []
    for side in (~after, after):
        ts = tau[side]
        X = np.column_stack([ts ** k for k in range(4)])
        c, *_ = np.linalg.lstsq(X, y_T[side], rcond=None)
        for t in ts[:: max(1, len(ts) // 8)]:
            rows.append(skew(np.array([1.0, t, t * t, t ** 3]) @ c))
            rhs.append(np.array([0.0, 1.0, 2 * t, 3 * t * t]) @ c)
    q = np.zeros(nq)
    q[:3] = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0]
    powers = np.column_stack([tau ** (k + 1) for k in range(degree)])  # (n, degree)
    step = after.astype(float)

    def rotations(qa):  # (..., na) -> (..., n, 3, 3)
        theta = np.einsum("nk,...kj->...nj", powers, qa.reshape(qa.shape[:-1] + (degree, 3)))
        return quat_to_dcm(quat_exp(-theta))

    def predict(q, R):
        v = q[na:na + 3] + tau[:, None] * q[na + 3:na + 6]
        return np.einsum("nij,nj->ni", R, v) + q[na + 6:na + 9] + step[:, None] * q[na + 9:]

    def linear_columns(R):  # ∂y/∂(B0, B1, h, d): (3n, 12)
        L = np.empty((n, 3, 12))
        L[:, :, 0:3], L[:, :, 3:6] = R, R * tau[:, None, None]
        L[:, :, 6:9] = np.eye(3)
        L[:, :, 9:12] = step[:, None, None] * np.eye(3)
        return L.reshape(3 * n, 12)

    R = rotations(q[:na])
    q[na:] = np.linalg.lstsq(linear_columns(R), y_T.ravel(), rcond=None)[0]
    prior = np.zeros(nq)
    prior[0:3] = 1.0 / ROTATION_PRIOR_RAD[0]
    prior[3:na] = 1.0 / ROTATION_PRIOR_RAD[1]
    prior[na + 3:na + 6] = 1.0 / b1_sigma_T
    prior[na + 6:na + 9] = 1.0 / OFFSET_PRIOR_T
    keep = prior > 0

    def cost(q, R):
        r = (y_T - predict(q, R)).ravel() / sigma_T
        return r, float(r @ r + np.sum((prior * q)[keep] ** 2))

    r, c0 = cost(q, R)
    lam, eps = 1e-3, 1e-6
    J = np.empty((3 * n, nq))
    last = iterations  # the pass that only takes the Jacobian at the solution
    for it in range(iterations + 1):
        if it:
            yield
        v = q[na:na + 3] + tau[:, None] * q[na + 3:na + 6]
        dq = q[:na] + eps * np.eye(na)  # every coefficient perturbed at once
        yp = np.einsum("mnij,nj->mni", rotations(dq), v) - np.einsum("nij,nj->ni", R, v)[None]
        J[:, :na] = (yp / eps).reshape(na, 3 * n).T
        J[:, na:] = linear_columns(R)
        J /= sigma_T
        Jf = np.vstack([J, np.diag(prior)[keep]])
        H = Jf.T @ Jf
        if it == last:  # the Jacobian at the solution: its covariance
            break
        g = Jf.T @ np.concatenate([r, -(prior * q)[keep]])
        try:
            dx = np.linalg.solve(H + lam * np.diag(np.diag(H)), g)
        except np.linalg.LinAlgError:
            return None
        q1 = q + dx
        R1 = rotations(q1[:na])
        r1, c1 = cost(q1, R1)
        if c1 <= c0:
            converged = c0 - c1 < 1e-9 * c0
            q, R, r, c0, lam = q1, R1, r1, c1, max(lam / 3.0, 1e-7)
            if converged:
                last = it + 1
        else:
            lam *= 10.0
    try:
        cov = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(cov)):
        return None
    dof = max(3 * n - nq, 1)
    var = np.maximum(np.sum(r.reshape(n, 3) ** 2, axis=0) * sigma_T ** 2 / (dof / 3.0), sigma_T ** 2)
    scale = max(float(r @ r) / dof, 1.0)
    return q[na + 9:].copy(), cov[na + 9:, na + 9:] * scale, float(np.sqrt(np.mean(var)))


@dataclass(frozen=True)
class Rest:
    """A channel at rest: screening s (leakage or 1) and rotor angle φ [rad]."""

    s: float
    phi_rad: float


@dataclass
class _Pending:
    channel: int
    t0_s: float  # last poll at rest before the motion
    t1_s: float  # first poll at rest after it
    a: Rest
    b: Rest


@dataclass
class _Cluster:
    """Motions of one or more channels that overlap in time: one step of the field, one observation."""

    t0_s: float
    t1_s: float
    c_a: np.ndarray  # per channel: s_B cos φ_B − s_A cos φ_A (0: the channel did not move)
    channels: tuple[int, ...]


class ChannelModel:
    """One channel's calibrated field: F_a (estimated, with covariance), F_b (design × scale)."""

    def __init__(self, geometry: MagnetGeometry, prior_frac: float) -> None:
        g = geometry
        a, u = np.asarray(g.home_axis, float), np.asarray(g.shaft_axis, float)
        self.geometry = g
        self.leakage = float(g.leakage)
        self.fa_design_T = dipole_field_T(g.moment_Am2 * a, g.position_m)
        self.fb_design_T = dipole_field_T(g.moment_Am2 * np.cross(u, a), g.position_m)
        self.fa_T = self.fa_design_T.copy()
        n = float(np.linalg.norm(self.fa_design_T))
        self.P = np.eye(3) * (prior_frac * n) ** 2
        self.steps = 0  # observations taken into F_a
        self.ill_conditioned = 0
        self.weak_steps = 0  # motions that do not change the open field (turns while closed)
        self.outliers = 0
        self.flagged = 0  # samples skipped because this channel moved
        self.last_innovation_T = math.nan  # |the step the model missed| at the latest transition (taken or not)
        self.last_fit_rms_T = math.nan

    @property
    def scale(self) -> float:
        n2 = float(self.fa_design_T @ self.fa_design_T)
        return float(self.fa_T @ self.fa_design_T) / n2

    @property
    def scale_sigma(self) -> float:
        d = self.fa_design_T / float(self.fa_design_T @ self.fa_design_T)
        return math.sqrt(max(float(d @ self.P @ d), 0.0))

    def field_T(self, rest: Rest) -> np.ndarray:
        c, s = math.cos(rest.phi_rad), math.sin(rest.phi_rad)
        return rest.s * (c * self.fa_T + s * self.scale * self.fb_design_T)


class KitFieldModel:
    """The kit's field at the sensor from the sequencer's channels (`fsw.deorbit.sequencer.Channel`)."""

    def __init__(self, channels, geometry=DESIGN, *, sigma_T: float = 1.5e-6, guard_s: float = 0.1,
                 window_s: float = 30.0, degree: int = 3, max_samples: int = 1024, prior_frac: float = 0.15,
                 max_sigma_frac: float = 0.05, chi2_max: float = CHI2_3_999, min_window_s: float = 3.0,
                 misfit: float = 1.1, max_fit_samples: int = 320, field_rate_T_per_s: float = 0.1e-6,
                 fit_steps_per_sample: int = 2, max_jobs: int = 3) -> None:
        if len(geometry) != len(channels):
            raise ValueError("one magnet geometry per kit channel")
        self.channels = channels
        self.models = [ChannelModel(g, prior_frac) for g in geometry]
        self.sigma_T = float(sigma_T)
        self.guard_s = float(guard_s)
        self.window_s = float(window_s)
        self.min_window_s = float(min_window_s)
        self.misfit = float(misfit)
        self.max_fit_samples = int(max_fit_samples)
        self.field_rate_T_per_s = float(field_rate_T_per_s)
        self.fit_steps_per_sample = int(fit_steps_per_sample)
        self.max_jobs = int(max_jobs)
        self._jobs: deque = deque()  # (evaluation generator, channels) of the steps, the first under way
        #: t_s -> the host's calibration then (`fsw.estimation.magcal.Calibration`: b_T, D) or None: the
        #: step fits see the field the host's iron leaves undistorted (set by the flight loop)
        self.host = None
        self.degree = int(degree)
        self.max_sigma_frac = float(max_sigma_frac)
        self.chi2_max = float(chi2_max)
        n = len(channels)
        self.rest: list[Rest | None] = [self._rest(i) for i in range(n)]
        self._from: list[Rest | None] = list(self.rest)
        self._t_rest = [math.nan] * n  # latest poll each channel was at rest
        #: motions [t0, t1, channel] of the channels, t1 = inf while it lasts
        self.intervals: deque[list] = deque(maxlen=16)
        self._open = [None] * n  # the interval of a channel's motion under way
        self.pending: list[_Pending] = []  # motions ended while another channel still moves
        self.clusters: list[_Cluster] = []  # steps waiting for their after-side samples
        self._strong: deque[tuple[float, float]] = deque(maxlen=16)  # spans of the steps of the open field
        # the channels' F_a jointly (a step of two channels at once observes their sum): x, P
        self.x_T = np.concatenate([m.fa_T for m in self.models])
        self.P = np.zeros((3 * n, 3 * n))
        for i, m in enumerate(self.models):
            self.P[3 * i:3 * i + 3, 3 * i:3 * i + 3] = m.P
        # accepted samples: time, raw field, the channels' rest states at that time
        self._samples: deque[tuple[float, np.ndarray, tuple]] = deque(maxlen=max_samples)
        self.flagged = 0
        self.polls = 0
        self.restored = False  # the calibration is one from before a restart (`restore`)
        # calibrations taken in (the flight loop re-expresses its gate's reference); each replaces x_T and P
        self.version = 0

    # --- state ------------------------------------------------------------------------------------
    def _rest(self, i: int) -> Rest | None:
        ch = self.channels[i]
        cap, st = ch.capsule, ch.stepper
        if cap.state is CapsuleState.CLOSED:
            s = self.models[i].leakage
        elif cap.state is CapsuleState.OPEN:
            s = 1.0
        else:
            return None  # opening, closing, or a fault: the screening is not known
        if st.moving or st.state in (MagnetState.TURNING, MagnetState.HOMING):
            return None
        return Rest(s, 2.0 * math.pi * (st.position_steps % STEPS_PER_TURN) / STEPS_PER_TURN)

    def poll(self, now_s: float) -> None:
        """Every loop tick: the channels' states now; a motion's start and end, a step to calibrate on."""
        self.polls += 1
        for i in range(len(self.channels)):
            r = self._rest(i)
            prev = self.rest[i]
            if r is None and prev is not None:  # a motion starts
                self._from[i] = prev
                t0 = self._t_rest[i] if math.isfinite(self._t_rest[i]) else now_s
                self._open[i] = [t0, math.inf, i]
                self.intervals.append(self._open[i])
            elif r is not None and prev is None:  # a motion ends
                if self._open[i] is not None:
                    self._open[i][1] = now_s
                    if self._from[i] is not None:
                        self.pending.append(_Pending(i, self._open[i][0], now_s, self._from[i], r))
                self._open[i] = None
            elif r is not None and prev is not None and r != prev:  # changed between two polls
                t0 = self._t_rest[i] if math.isfinite(self._t_rest[i]) else now_s
                self.intervals.append([t0, now_s, i])
                self.pending.append(_Pending(i, t0, now_s, prev, r))
            elif r is None and prev is None and self._open[i] is None:  # in motion from the start
                self._open[i] = [now_s, math.inf, i]
                self.intervals.append(self._open[i])
            if r is not None:
                self._t_rest[i] = now_s
            self.rest[i] = r
        if self.pending and all(r is not None for r in self.rest):
            self._close_cluster()

    def _close_cluster(self) -> None:
        """Everything has come to rest: the motions since the last rest of all channels are one step."""
        c_a = np.zeros(len(self.channels))
        first: dict[int, Rest] = {}
        last: dict[int, Rest] = {}
        for p in self.pending:
            first.setdefault(p.channel, p.a)
            last[p.channel] = p.b
        for i, a in first.items():
            b = last[i]
            c_a[i] = b.s * math.cos(b.phi_rad) - a.s * math.cos(a.phi_rad)
        c = _Cluster(min(p.t0_s for p in self.pending), max(p.t1_s for p in self.pending), c_a, tuple(sorted(first)))
        self.clusters.append(c)
        if float(np.max(np.abs(c_a))) >= 0.5:
            self._strong.append((c.t0_s, c.t1_s))
        self.pending = []

    @property
    def unscreened(self) -> bool:
        """Whether a capsule is open (or not known closed): its magnet's field at the sensor (~80 µT at
        0.3 m) is then taken out with a model a few µT off (what its calibration's steps leave on a
        tumble), an error the host's calibration would take for hard iron and carry into the closed
        samples after. Closed, the leakage's error is a few hundredths of a µT."""
        return any(r is None or r.s >= 1.0 for r in self.rest)

    def moved_between(self, t0_s: float, t1_s: float, channel: int | None = None) -> bool:
        """Whether `channel` (None: any) moved in [t0_s, t1_s] or within `guard_s` of it: a sample at t is
        flagged when it moved in [t, t]; the magnetometer's driver keeps an offset measurement spread over
        such a span out of its mean (a capsule closing meanwhile steps the field by tens of µT)."""
        g = self.guard_s
        return any(t0 - g <= t1_s and t0_s <= t1 + g for t0, t1, i in self.intervals
                   if channel is None or i == channel)

    def coefficients(self) -> np.ndarray | None:
        """Per channel the coefficient of its F_a in the modelled field now (s cos φ of its rest state);
        None while a channel is not at rest."""
        if any(r is None for r in self.rest):
            return None
        return np.array([r.s * math.cos(r.phi_rad) for r in self.rest])

    def error_cov_T2(self, c: np.ndarray, P: np.ndarray | None = None) -> np.ndarray:
        """The covariance [T²] of the model's error in a field c_pitch F_a,pitch + c_yaw F_a,yaw (with the
        calibration's covariance `P`, default the current one): for the coefficients' change between two
        states, how much the error of the kit-compensated samples can step there."""
        H = np.kron(np.asarray(c, float)[None, :], np.eye(3))
        return H @ (self.P if P is None else P) @ H.T

    def model_T(self) -> np.ndarray:
        """The modelled field now, the channels at rest in their current (or last) state [T]."""
        return self._model(tuple(r if r is not None else (f or Rest(m.leakage, 0.0))
                                 for m, r, f in zip(self.models, self.rest, self._from)))

    def field_at(self, t_s: float) -> tuple[np.ndarray, bool]:
        """(the kit's modelled field at the sensor for a sample at `t_s` [T], skip it): a sample taken
        while something moved is skipped (its field is still the best guess, from the last rest)."""
        b = self._model(tuple(r if r is not None else f for r, f in zip(self.rest, self._from)))
        skip = False
        for i, m in enumerate(self.models):
            if self.rest[i] is None or self.moved_between(t_s, t_s, i):
                m.flagged += 1
                skip = True
        self.flagged += skip
        return b, skip

    # --- calibration ------------------------------------------------------------------------------
    def record(self, t_s: float, raw_T: np.ndarray, advance: bool = True) -> None:
        """An accepted, unflagged sample (the sensor's own): kept for the step fits; a step whose
        after-side is complete (`window_s`, or cut by the next motion) is queued for its evaluation, and
        (`advance`) the evaluation under way advanced by :meth:`due` iterations (a fit of a few hundred
        samples takes 5-20 of ~1-3 ms each: spread over the samples, it never holds the loop; a new
        calibration is taken in when it ends). Past `max_jobs` + 1 queued, the oldest waiting step is
        dropped (counted ``ill_conditioned``). The flight loop advances it itself, in ticks with room."""
        if any(r is None for r in self.rest):
            return
        self._samples.append((float(t_s), np.array(raw_T, dtype=float), tuple(self.rest)))
        keep = []
        for c in self.clusters:
            nxt = min((t0 for t0, _, _ in self.intervals if t0 > c.t1_s), default=math.inf)
            if t_s >= min(c.t1_s + self.window_s, nxt):
                if len(self._jobs) > self.max_jobs:  # behind: the oldest waiting step is not evaluated
                    for i in self._jobs[1][1]:
                        self.models[i].ill_conditioned += 1
                    del self._jobs[1]
                self._jobs.append((self._evaluate(c, nxt), c.channels))
            else:
                keep.append(c)
        self.clusters = keep
        if advance:
            self.advance(self.due())

    def due(self) -> int:
        """Iterations of the step fits due for a sample: `fit_steps_per_sample` per step queued (more
        while steps wait)."""
        return self.fit_steps_per_sample * len(self._jobs)

    def advance(self, iterations: int = 1) -> None:
        """The queued evaluations advanced by up to `iterations` iterations of their fits."""
        for _ in range(iterations):
            if not self._jobs:
                break
            try:
                next(self._jobs[0][0])
            except StopIteration:
                self._jobs.popleft()

    @property
    def evaluating(self) -> int:
        """Steps queued or being evaluated."""
        return len(self._jobs)

    def _evaluate(self, c: _Cluster, t_next_s: float):
        """The step of the field across the motions of `c`, from a fit on both sides (a generator of the
        fit's iterations): over `window_s` each side, halved while the fit's residual exceeds `misfit`
        times the sensor's noise (the rotation's polynomial follows a fast tumble only so far), down to
        `min_window_s`."""
        involved = [self.models[i] for i in c.channels]
        if float(np.max(np.abs(c.c_a))) < 0.5:  # no step of the open field (a turn while closed)
            for m in involved:
                m.weak_steps += 1
            return
        w, fit = self.window_s, None
        while True:
            trial = yield from self._fit(c, t_next_s, w)
            if trial is not None:
                fit = trial
            if trial is None or trial[2] <= self.misfit * self.sigma_T or w / 2 < self.min_window_s:
                break
            w /= 2
        if fit is None:
            for m in involved:
                m.ill_conditioned += 1
            return
        d, R, rms = fit
        for m in involved:
            m.last_fit_rms_T = rms
        self._update(c, d, R)

    def _fit(self, c: _Cluster, t_next_s: float, w: float):
        """A generator of the fit's iterations returning (the step d the model missed, its covariance, the
        residual RMS per axis) from the samples within `w` of the motions, or None (too few samples on a
        side, singular).

        d = Σ c_a,i (F_a,i true − F_a,i) + noise."""
        g = self.guard_s
        # the fit reaches back to the previous step of an open field (a turn while closed moves only the
        # leakage, which the samples are compensated for)
        prev_end = max((t1 for _, t1 in self._strong if t1 < c.t0_s), default=-math.inf)
        lo, hi = max(c.t0_s - w, prev_end + g), min(c.t1_s + w, t_next_s - g)
        rows = [(t, raw, st) for t, raw, st in self._samples
                if (lo <= t < c.t0_s - g) or (c.t1_s + g < t <= hi)]
        if len(rows) > self.max_fit_samples:  # fast sampling: every k-th sample is plenty (CPU budget)
            rows = rows[::-(-len(rows) // self.max_fit_samples)]
        n_pre = sum(1 for t, _, _ in rows if t < c.t0_s)
        need = self.degree + 5
        if n_pre < need or len(rows) - n_pre < need:
            return None
        t_m = 0.5 * (c.t0_s + c.t1_s)
        tau = np.array([(t - t_m) / w for t, _, _ in rows])
        y = np.array([raw - self._model(st) for _, raw, st in rows])
        cal = self.host(t_m) if self.host is not None else None
        if cal is not None:  # (I + D)(y − b): the step d in it is (I + D) times the sensor's
            A = np.eye(3) + cal.D
            y = (y - cal.b_T) @ A.T
        fit = yield from rotating_step_fit_steps(tau, tau > 0, y, self.sigma_T, self.field_rate_T_per_s * w,
                                                 self.degree)
        if fit is None or cal is None:
            return fit
        d, R, rms = fit
        Ai = np.linalg.inv(A)
        return Ai @ d, Ai @ R @ Ai.T, rms

    def _model(self, states: tuple) -> np.ndarray:
        """The modelled field of the channels in `states` (a channel whose state is None: none)."""
        b = np.zeros(3)
        for m, r in zip(self.models, states):
            if r is not None:
                b += m.field_T(r)
        return b

    def _update(self, c: _Cluster, d: np.ndarray, R: np.ndarray) -> None:
        """A Kalman update of the channels' F_a (constants) with the missed step `d`, unless the
        observation is ill-conditioned or an outlier (then the last good calibration stays)."""
        involved = [self.models[i] for i in c.channels]
        for m in involved:
            m.last_innovation_T = float(np.linalg.norm(d))
        c_max = float(np.max(np.abs(c.c_a)))
        n_design = min(float(np.linalg.norm(m.fa_design_T)) for m in involved)
        if float(np.sqrt(np.max(np.diag(R)))) / c_max > self.max_sigma_frac * n_design:
            for m in involved:
                m.ill_conditioned += 1
            return
        H = np.kron(c.c_a[None, :], np.eye(3))
        S = H @ self.P @ H.T + R
        chi2 = float(d @ np.linalg.solve(S, d))
        K = self.P @ H.T @ np.linalg.inv(S)
        x = self.x_T + K @ d
        ratios = [float(np.linalg.norm(x[3 * i:3 * i + 3]) / np.linalg.norm(self.models[i].fa_design_T))
                  for i in c.channels]
        if chi2 > self.chi2_max or not all(0.5 <= q <= 1.5 for q in ratios):
            for m in involved:
                m.outliers += 1
            return
        P = (np.eye(len(x)) - K @ H) @ self.P
        self.x_T, self.P = x, 0.5 * (P + P.T)
        for i, m in enumerate(self.models):
            m.fa_T = self.x_T[3 * i:3 * i + 3].copy()
            m.P = self.P[3 * i:3 * i + 3, 3 * i:3 * i + 3].copy()
        for m in involved:
            m.steps += 1
        self.version += 1

    # --- across a restart (`fsw.persist`) ---------------------------------------------------------
    def snapshot(self) -> dict | None:
        """The channels' calibrated F_a [T] and their covariance to keep, with the design's F_a (a model of
        another kit refuses it), and the steps taken in (None before any)."""
        if self.version == 0:
            return None
        return {"fa_T": [float(x) for x in self.x_T], "P": [[float(x) for x in row] for row in self.P],
                "fa_design_T": [float(x) for m in self.models for x in m.fa_design_T],
                "steps": [m.steps for m in self.models]}

    def restore(self, snap: dict) -> None:
        """The calibration from before a restart taken as the prior of the channels' F_a; the steps after
        it judge it as they judge any (outliers refused). ValueError when `snap` is not of this kit."""
        x = np.asarray(snap["fa_T"], float)
        P = np.asarray(snap["P"], float)
        design = np.asarray(snap["fa_design_T"], float)
        n = 3 * len(self.models)
        if x.shape != (n,) or P.shape != (n, n) or design.shape != (n,) or not (
                np.all(np.isfinite(x)) and np.all(np.isfinite(P))):
            raise ValueError("kit-field calibration of the wrong shape or not finite")
        mine = np.concatenate([m.fa_design_T for m in self.models])
        if not np.allclose(design, mine, rtol=1e-9, atol=1e-15):
            raise ValueError("kit-field calibration of another kit's design")
        ev = np.linalg.eigvalsh(0.5 * (P + P.T)) if np.allclose(P, P.T, rtol=1e-9, atol=0.0) else np.array([-1.0])
        if np.max(ev) <= 0 or np.min(ev) < -1e-9 * np.max(ev):
            raise ValueError("kit-field covariance not symmetric positive")
        self.x_T, self.P = x, P
        for i, m in enumerate(self.models):
            m.fa_T = x[3 * i:3 * i + 3].copy()
            m.P = P[3 * i:3 * i + 3, 3 * i:3 * i + 3].copy()
            m.steps = int(snap.get("steps", [0] * len(self.models))[i])
        self.restored = True
        self.version += 1

    # --- telemetry --------------------------------------------------------------------------------
    def telemetry(self, now_s: float, tlm) -> None:
        """DEBRIS_KIT_FIELD, one per channel."""
        for i, (m, r) in enumerate(zip(self.models, self.rest)):
            b = m.field_T(r if r is not None else (self._from[i] or Rest(m.leakage, 0.0)))
            tlm.kit_field(now_s, i, scale=m.scale, scale_sigma=m.scale_sigma, field_T=b,
                          innovation_T=m.last_innovation_T, fit_rms_T=m.last_fit_rms_T, steps=m.steps,
                          ill_conditioned=m.ill_conditioned, outliers=m.outliers, flagged=m.flagged,
                          moving=r is None)
