"""Detumbling with the de-orbit kit: a discrete B-dot-like law of the kit's own pulses.

Each channel's magnet (dipole p_c along its home axis, polarity ±1, screened or not) puts the moment
M = p × B on the spacecraft; its power on the tumble is ω·M = s·ω·(p_c × B). A dipole fixed in a body
that turns fast does no work on average over a turn (B seen from the body turns about ω), so the law
switches with the turn: at every decision (period `period_s`, a few seconds) it predicts the field seen
from the body over the next pulse — B_body(t) = exp(−[ω×] t) B_body(t₀), the field fixed in inertial
space over seconds — and for each channel integrates ω·(p_c × B) from the time the capsule would be open
(`open_delay_s`, plus `turn_delay_s` when the magnet has to turn over first) to the end of the pulse. The
polarity that makes the integral negative is chosen (the kit takes energy out of the tumble); ω over the
pulse follows the torque-free Euler's equations with the tensor the box has (`inertia_kgm2`, the
identified one in the mission); a channel whose best integral is less than `min_fraction` of what a
dipole aligned with B × ω would do is closed (the pulse would cost more than it does). Pulses are
`period_s + overlap_s` long, so that a channel kept at the same polarity stays open from one decision
to the next (`Sequencer.pulse` extends it).

Trust: the law acts only on a rate whose 1-σ (largest axis) is within `max_rate_sigma_radps` and a field
sample no older than `max_sample_age_s`; otherwise it closes both capsules (a pulse on a wrong rate can
spin the tumble up). Pure computation: no hardware, no clock.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .controller import ChannelCommand
from .kit_field import DESIGN, MagnetGeometry


@dataclass(frozen=True)
class DetumbleConfig:
    period_s: float = 6.0                 # a decision every period
    overlap_s: float = 1.5                # pulses outlast the period by this (kept open across decisions)
    open_delay_s: float = 2.0             # the shutter's opening ramp
    turn_delay_s: float = 1.5             # close + half a turn before a polarity change opens again
    min_fraction: float = 0.2             # of the aligned dipole's work, below which a channel stays closed
    max_rate_sigma_radps: float = math.radians(0.3)
    max_sample_age_s: float = 5.0
    step_s: float = 0.5                   # the prediction's step

    def __post_init__(self) -> None:
        if not (self.period_s > 0 and self.overlap_s >= 0 and self.open_delay_s >= 0 and self.turn_delay_s >= 0
                and 0 <= self.min_fraction < 1 and self.max_rate_sigma_radps > 0 and self.step_s > 0):
            raise ValueError("bad detumble configuration")


def rotate_about(v: np.ndarray, axis_angle: np.ndarray) -> np.ndarray:
    """`v` turned by the rotation vector `axis_angle` (Rodrigues)."""
    th = float(np.linalg.norm(axis_angle))
    if th < 1e-12:
        return v.copy()
    k = axis_angle / th
    return v * math.cos(th) + np.cross(k, v) * math.sin(th) + k * float(k @ v) * (1.0 - math.cos(th))


def predict(omega_radps: np.ndarray, b_body_T: np.ndarray, t1_s: float, J_kgm2: np.ndarray | None,
            step_s: float = 0.5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Times (n,), ω (n, 3) and B in body axes (n, 3) from now to `t1_s`: torque-free Euler's equations
    with `J_kgm2` (None: ω held), the field fixed in inertial space seen from the turning body."""
    n = max(2, int(math.ceil(t1_s / step_s)) + 1)
    ts = np.linspace(0.0, t1_s, n)
    h = ts[1] - ts[0]
    w = np.empty((n, 3))
    b = np.empty((n, 3))
    w[0], b[0] = omega_radps, b_body_T
    J_inv = None if J_kgm2 is None else np.linalg.inv(J_kgm2)

    def wdot(x):
        return np.zeros(3) if J_inv is None else -J_inv @ np.cross(x, J_kgm2 @ x)

    for k in range(n - 1):
        x = w[k]
        k1 = wdot(x)
        k2 = wdot(x + 0.5 * h * k1)
        k3 = wdot(x + 0.5 * h * k2)
        k4 = wdot(x + h * k3)
        w[k + 1] = x + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        b[k + 1] = rotate_about(b[k], -0.5 * (w[k] + w[k + 1]) * h)
    return ts, w, b


def work_J(omega_radps: np.ndarray, b_body_T: np.ndarray, dipole_Am2: np.ndarray, t0_s: float,
           t1_s: float, J_kgm2: np.ndarray | None = None, step_s: float = 0.5) -> float:
    """∫ ω·(p × B) dt over [t0, t1] from now (trapezoid on `predict`'s grid), the dipole `p` held."""
    if t1_s <= t0_s:
        return 0.0
    ts, w, b = predict(omega_radps, b_body_T, t1_s, J_kgm2, step_s)
    return _work(ts, w, b, dipole_Am2, t0_s)


def _work(ts, w, b, dipole_Am2, t0_s: float) -> float:
    power = np.einsum("ij,ij->i", w, np.cross(dipole_Am2, b))
    keep = ts >= t0_s - 1e-9
    if keep.sum() < 2:
        return 0.0
    return float(np.trapezoid(power[keep], ts[keep]))


class DetumbleLaw:
    """The kit's pulse law while detumbling (`DeorbitKit.law`): `update_rate` and `update_field` feed it,
    `decide(now_s, channels)` returns a :class:`ChannelCommand` per channel."""

    def __init__(self, config: DetumbleConfig = DetumbleConfig(),
                 magnets: tuple[MagnetGeometry, ...] = DESIGN, inertia_kgm2=None) -> None:
        """`inertia_kgm2` (3, 3): the tensor the prediction of ω uses (None: ω held over a pulse)."""
        self.config = config
        self.J_kgm2 = None if inertia_kgm2 is None else np.asarray(inertia_kgm2, float)
        self.period_s = config.period_s
        self.axes = [m.moment_Am2 * np.asarray(m.home_axis, float) for m in magnets]
        self.omega_radps: np.ndarray | None = None
        self.rate_sigma_radps = math.inf
        self.b_T: np.ndarray | None = None
        self.t_b_s = -math.inf
        self.reason = "no rate yet"
        #: set by the mission: every capsule stays closed, and this is why (e.g. an estimate converging)
        self.quiet_reason = ""
        self.decisions = 0
        self.held = 0

    def update_rate(self, omega_radps: np.ndarray, sigma_radps: float) -> None:
        self.omega_radps = np.asarray(omega_radps, float).copy()
        self.rate_sigma_radps = float(sigma_radps)

    def update_field(self, t_s: float, b_T: np.ndarray) -> None:
        """A calibrated, kit-compensated field sample (body axes)."""
        self.b_T = np.asarray(b_T, float).copy()
        self.t_b_s = float(t_s)

    def _why_not(self, now_s: float) -> str:
        c = self.config
        if self.quiet_reason:
            return self.quiet_reason
        if self.omega_radps is None:
            return "no rate yet"
        if not self.rate_sigma_radps <= c.max_rate_sigma_radps:
            return (f"rate sigma {math.degrees(self.rate_sigma_radps):.3f} deg/s > "
                    f"{math.degrees(c.max_rate_sigma_radps):g}")
        if self.b_T is None or now_s - self.t_b_s > c.max_sample_age_s:
            return "no recent field sample"
        return ""

    def choose(self, now_s: float, polarity: tuple[int, ...]) -> list[tuple[int, float]]:
        """(polarity ±1 or 0, predicted work J) per channel; `polarity` the magnets' polarities now."""
        c = self.config
        why = self._why_not(now_s)
        self.reason = why
        if why:
            return [(0, 0.0)] * len(self.axes)
        w = self.omega_radps
        b0 = rotate_about(self.b_T, -w * (now_s - self.t_b_s))  # the field now
        end = c.period_s + c.overlap_s
        ts, ws, bs = predict(w, b0, end, self.J_kgm2, c.step_s)
        out = []
        for axis, pol in zip(self.axes, polarity):
            best = (0, 0.0)
            for s in (1, -1):
                start = c.open_delay_s + (c.turn_delay_s if pol != s else 0.0)
                wk = _work(ts, ws, bs, s * axis, start)
                if wk < best[1]:
                    best = (s, wk)
            # the work of a dipole of this size along B × ω over the same time: the most there is
            bxw = np.cross(b0, w)
            ideal = -float(np.linalg.norm(axis) * np.linalg.norm(bxw)) * (end - c.open_delay_s)
            if best[0] and best[1] > c.min_fraction * ideal:  # too little (both negative numbers)
                best = (0, best[1])
            out.append(best)
        return out

    def decide(self, now_s: float, channels) -> list[ChannelCommand]:
        """The kit's decision: each channel's pulse (or closed); `channels` the sequencer's."""
        self.decisions += 1
        chosen = self.choose(now_s, tuple(int(ch.polarity) for ch in channels))
        if self.reason:
            self.held += 1
        width = self.config.period_s + self.config.overlap_s
        return [ChannelCommand(i, s, width if s else 0.0, 0.0, 0.0) for i, (s, _) in enumerate(chosen)]
