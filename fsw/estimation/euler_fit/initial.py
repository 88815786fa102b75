"""Starting values of the fit from the samples alone: segment lengths, rough rates per segment and a
chain of segment attitudes (:func:`retilt` also re-chains them between the multiple-shooting stages)."""
from __future__ import annotations

import math

import numpy as np

from ..rotations import quat_aligning, quat_conj, quat_exp, quat_mul
from .propagation import body_from_inertial


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


def turn_rate(t_s: np.ndarray, b_T: np.ndarray, k: int = 5) -> float:
    """Median rate [rad/s] at which the measured field direction turns, over k-sample steps (the part of
    ω across B; a lower bound of |ω|)."""
    b = np.asarray(b_T, float)
    t = np.asarray(t_s, float)
    k = max(1, min(k, len(t) - 1))
    u = b / np.linalg.norm(b, axis=1, keepdims=True)
    c = np.clip(np.sum(u[k:] * u[:-k], axis=1), -1.0, 1.0)
    return float(np.median(np.arccos(c) / (t[k:] - t[:-k])))


def segment_length(t_s: np.ndarray, b_T: np.ndarray, max_samples: int, angle_rad: float) -> int:
    """Samples per segment: about ``angle_rad`` of turn of the field, within [8, ``max_samples``]."""
    dt = float(np.median(np.diff(t_s)))
    w = turn_rate(t_s, b_T)
    L = max_samples if w <= 0 else int(round(angle_rad / (w * dt)))
    return int(np.clip(L, 8, max_samples))


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
