"""Rotations: cross-product matrices, the SO(3) exponential and its right Jacobian, unit quaternions and
direction cosine matrices — the one copy the flight software, the simulator and the ground tools share.

Conventions. A quaternion is scalar first, q = [w, x, y, z], and rotates body axes into the reference
(inertial) axes: v_I = R(q) v_B, R = R_bodyToInertial. The product is Hamilton's, so that
R(p ⊗ q) = R(p) R(q). A rotation vector φ is axis × angle [rad]; exp([φ]ₓ) is its rotation matrix.

Shapes. The quaternion helpers take one quaternion (4,) / rotation vector (3,) or a stack (..., 4) /
(..., 3) (the batched output-error fit); one vector is worked out with scalar arithmetic (the filters
call these once per sample, where numpy's per-call overhead would dominate), a stack with the same
formulas vectorised. `so3_exp`, `so3_right_jacobian`, `quat_log`, `quat_aligning`, `quat_from_dcm` and
`rotvec_from_dcm` take one vector or matrix.

Compiled kernels keep their own inlined arithmetic where calling a Python helper per step would cost
more than the step: fsw/estimation/rate_kf.py (the flown filter; it calls :func:`jr_coefficients`, which
is compiled) and rate_formulas._skew_ij. The attitude filter's RK4 substeps use the float-tuple forms
:func:`quat_mul_tuple` and :func:`so3_exp_jr_tuple` below for the same reason.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["skew", "jr_coefficients", "so3_exp", "so3_right_jacobian", "quat_mul", "quat_conj", "quat_exp",
           "quat_log", "quat_normalize", "quat_to_dcm", "quat_from_dcm", "rotvec_from_dcm", "quat_aligning",
           "quat_mul_tuple", "so3_exp_jr_tuple"]


# --- SO(3) -------------------------------------------------------------------------------------------

def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices [v]ₓ for v of shape (..., 3): [v]ₓ u = v × u."""
    v = np.asarray(v)
    s = np.zeros(v.shape[:-1] + (3, 3))
    s[..., 0, 1], s[..., 0, 2] = -v[..., 2], v[..., 1]
    s[..., 1, 0], s[..., 1, 2] = v[..., 2], -v[..., 0]
    s[..., 2, 0], s[..., 2, 1] = -v[..., 1], v[..., 0]
    return s


@njit(cache=True)
def jr_coefficients(th2: float) -> tuple[float, float]:
    """(1 − cos θ)/θ² and (θ − sin θ)/θ³ for θ² = `th2`, with their series near θ = 0 (compiled: the
    flown filter's step calls it)."""
    if th2 < 1e-6:
        return 0.5 - th2 / 24.0, 1.0 / 6.0 - th2 / 120.0
    th = math.sqrt(th2)
    return (1.0 - math.cos(th)) / th2, (th - math.sin(th)) / (th2 * th)


def so3_exp(phi: np.ndarray) -> np.ndarray:
    """Rotation matrix exp([φ]ₓ) of a rotation vector φ (Rodrigues)."""
    th2 = float(phi @ phi)
    K = skew(phi)
    if th2 < 1e-12:
        return np.eye(3) + K + 0.5 * K @ K
    th = math.sqrt(th2)
    return np.eye(3) + (math.sin(th) / th) * K + ((1.0 - math.cos(th)) / th2) * K @ K


def so3_right_jacobian(phi: np.ndarray) -> np.ndarray:
    """J_r(φ) = ∫₀¹ exp(−[φ]ₓ s) ds = I − (1 − cos θ)/θ² [φ]ₓ + (θ − sin θ)/θ³ [φ]ₓ²."""
    a, c = jr_coefficients(float(phi @ phi))
    K = skew(phi)
    return np.eye(3) - a * K + c * K @ K


# --- quaternions -------------------------------------------------------------------------------------

def _parts(q) -> np.ndarray:
    """Components along the last axis first: w, x, y, z = _parts(q) (scalars for one quaternion)."""
    return np.moveaxis(np.asarray(q, float), -1, 0)


def _join(parts: list) -> np.ndarray:
    """Inverse of :func:`_parts`: components → (..., k)."""
    return np.array(parts) if np.ndim(parts[0]) == 0 else np.stack(parts, axis=-1)


def quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product p ⊗ q of scalar-first quaternions (R(p ⊗ q) = R(p) R(q)); (4,) or (..., 4)."""
    pw, px, py, pz = _parts(p)
    qw, qx, qy, qz = _parts(q)
    return _join([pw * qw - px * qx - py * qy - pz * qz, pw * qx + px * qw + py * qz - pz * qy,
                  pw * qy - px * qz + py * qw + pz * qx, pw * qz + px * qy - py * qx + pz * qw])


def quat_conj(q: np.ndarray) -> np.ndarray:
    """Conjugate [w, −x, −y, −z] (the inverse rotation of a unit quaternion); (4,) or (..., 4)."""
    return np.asarray(q, float) * np.array([1.0, -1.0, -1.0, -1.0])


def quat_exp(phi: np.ndarray) -> np.ndarray:
    """Unit quaternion(s) (..., 4) of rotation vector(s) φ (..., 3)."""
    phi = np.asarray(phi, float)
    if phi.ndim == 1:  # the squares summed in the stack's order (a BLAS dot may fuse them: 1 ulp apart)
        th = math.sqrt(float(phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]))
        s = 0.5 if th < 1e-12 else math.sin(0.5 * th) / th
        return np.array([math.cos(0.5 * th), s * phi[0], s * phi[1], s * phi[2]])
    th = np.linalg.norm(phi, axis=-1, keepdims=True)
    small = th < 1e-12
    s = np.where(small, 0.5, np.sin(0.5 * th) / np.where(small, 1.0, th))
    return np.concatenate([np.cos(0.5 * th), s * phi], axis=-1)


def quat_log(q: np.ndarray) -> np.ndarray:
    """Rotation vector of a unit quaternion (the shorter way round)."""
    if q[0] < 0:
        q = -q
    v = q[1:]
    s = math.sqrt(float(v @ v))
    if s < 1e-12:
        return 2.0 * v
    return (2.0 * math.atan2(s, q[0]) / s) * v


def quat_normalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternion in the direction of `q` (4,); ValueError for a zero or non-finite `q`."""
    q = np.asarray(q, dtype=float)
    if q.shape != (4,):
        raise ValueError(f"quaternion must have shape (4,), got {q.shape}")
    n = float(np.sqrt(q @ q))
    if not np.isfinite(n) or n == 0.0:
        raise ValueError(f"quaternion must be finite and nonzero, got {q}")
    return q / n


def quat_to_dcm(q: np.ndarray) -> np.ndarray:
    """R_bodyToInertial (..., 3, 3) of quaternion(s) [w, x, y, z] (..., 4).

    A non-unit q is taken as its normalised direction (the factor s = 2/|q|² does that without a
    separate division)."""
    w, x, y, z = _parts(q)
    s = 2.0 / (w * w + x * x + y * y + z * z)
    xx, yy, zz = s * x * x, s * y * y, s * z * z
    xy, xz, yz = s * x * y, s * x * z, s * y * z
    wx, wy, wz = s * w * x, s * w * y, s * w * z
    R = np.empty(np.shape(w) + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 0, 2] = 1.0 - (yy + zz), xy - wz, xz + wy
    R[..., 1, 0], R[..., 1, 1], R[..., 1, 2] = xy + wz, 1.0 - (xx + zz), yz - wx
    R[..., 2, 0], R[..., 2, 1], R[..., 2, 2] = xz - wy, yz + wx, 1.0 - (xx + yy)
    return R


def quat_from_dcm(R: np.ndarray) -> np.ndarray:
    """Unit quaternion [w, x, y, z] with w ≥ 0 of a rotation matrix (Shepperd 1978: from the largest of
    the trace and the diagonal, so that no division is by a small number)."""
    R = np.asarray(R, float)
    tr = float(np.trace(R))
    i = int(np.argmax([tr, R[0, 0], R[1, 1], R[2, 2]]))
    if i == 0:
        w = 0.5 * math.sqrt(1.0 + tr)
        q = [w, (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w)]
    elif i == 1:
        x = 0.5 * math.sqrt(1.0 + 2 * R[0, 0] - tr)
        q = [(R[2, 1] - R[1, 2]) / (4 * x), x, (R[0, 1] + R[1, 0]) / (4 * x), (R[0, 2] + R[2, 0]) / (4 * x)]
    elif i == 2:
        y = 0.5 * math.sqrt(1.0 + 2 * R[1, 1] - tr)
        q = [(R[0, 2] - R[2, 0]) / (4 * y), (R[0, 1] + R[1, 0]) / (4 * y), y, (R[1, 2] + R[2, 1]) / (4 * y)]
    else:
        z = 0.5 * math.sqrt(1.0 + 2 * R[2, 2] - tr)
        q = [(R[1, 0] - R[0, 1]) / (4 * z), (R[0, 2] + R[2, 0]) / (4 * z), (R[1, 2] + R[2, 1]) / (4 * z), z]
    q = np.array(q)
    return q / (np.linalg.norm(q) if q[0] >= 0 else -np.linalg.norm(q))


def rotvec_from_dcm(R: np.ndarray) -> np.ndarray:
    """Rotation vector (axis × angle, angle in [0, π]) of a rotation matrix."""
    c = max(-1.0, min(1.0, 0.5 * (np.trace(R) - 1.0)))
    angle = math.acos(c)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if angle < 1e-9:
        return 0.5 * w
    if math.pi - angle < 1e-6:  # 180°: axis from the diagonal
        axis = np.sqrt(np.maximum((np.diag(R) + 1.0) / 2.0, 0.0))
        i = int(np.argmax(axis))
        axis[(i + 1) % 3] = math.copysign(axis[(i + 1) % 3], R[i, (i + 1) % 3])
        axis[(i + 2) % 3] = math.copysign(axis[(i + 2) % 3], R[i, (i + 2) % 3])
        return angle * axis / np.linalg.norm(axis)
    return angle / (2.0 * math.sin(angle)) * w


def quat_aligning(b_body: np.ndarray, b_inertial: np.ndarray, angle_about_b_rad: float = 0.0) -> np.ndarray:
    """An attitude q (body → inertial) with R(q) b̂_body = b̂_inertial, turned by `angle_about_b_rad`
    about the body's field direction: the attitudes that one field sample allows."""
    a = np.asarray(b_inertial, float) / np.linalg.norm(b_inertial)
    b = np.asarray(b_body, float) / np.linalg.norm(b_body)
    v = np.cross(b, a)
    s, c = float(np.linalg.norm(v)), float(b @ a)
    if s > 1e-12:
        q = quat_exp(v / s * math.atan2(s, c))
    elif c > 0:
        q = np.array([1.0, 0.0, 0.0, 0.0])
    else:  # opposite: half a turn about any axis perpendicular to b
        axis = np.cross(b, [1.0, 0.0, 0.0] if abs(b[0]) < 0.9 else [0.0, 1.0, 0.0])
        q = quat_exp(axis / np.linalg.norm(axis) * math.pi)
    return quat_mul(q, quat_exp(b * angle_about_b_rad))


# --- float-tuple forms for Python inner loops ------------------------------------------------------------
# The same formulas as quat_mul, so3_exp and so3_right_jacobian on tuples of floats: the attitude filter's
# RK4 substeps (attitude_kalman.py) call them several times per substep, where creating arrays would cost
# more than the arithmetic.

def quat_mul_tuple(p: tuple, q: tuple) -> tuple:
    """p ⊗ q on 4-tuples of floats."""
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return (pw * qw - px * qx - py * qy - pz * qz, pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx, pw * qz + px * qy - py * qx + pz * qw)


def so3_exp_jr_tuple(px: float, py: float, pz: float) -> tuple[tuple, tuple]:
    """exp([φ]ₓ) and J_r(φ) as row-major 9-tuples."""
    th2 = px * px + py * py + pz * pz
    a, c = jr_coefficients(th2)
    s = 1.0 - th2 * c
    k2 = (px * px - th2, px * py, px * pz, px * py, py * py - th2, py * pz, px * pz, py * pz, pz * pz - th2)
    K = (0.0, -pz, py, pz, 0.0, -px, -py, px, 0.0)
    eye = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    E = tuple(i + s * k + a * kk for i, k, kk in zip(eye, K, k2))
    Jr = tuple(i - a * k + c * kk for i, k, kk in zip(eye, K, k2))
    return E, Jr


# --- compiled array forms for numba kernels ----------------------------------------------------------------
# quat_to_dcm, quat_mul, quat_exp and skew on one (4,) / (3,) array, compiled: called from other compiled
# kernels (the orbital-attitude filter's propagation, the ground smoothers' passes). Division as numpy does it.

@njit(cache=True, error_model="numpy")
def skew_nb(v):
    s = np.zeros((3, 3))
    s[0, 1], s[0, 2] = -v[2], v[1]
    s[1, 0], s[1, 2] = v[2], -v[0]
    s[2, 0], s[2, 1] = -v[1], v[0]
    return s


@njit(cache=True, error_model="numpy")
def quat_mul_nb(p, q):
    return np.array((p[0] * q[0] - p[1] * q[1] - p[2] * q[2] - p[3] * q[3],
                     p[0] * q[1] + p[1] * q[0] + p[2] * q[3] - p[3] * q[2],
                     p[0] * q[2] - p[1] * q[3] + p[2] * q[0] + p[3] * q[1],
                     p[0] * q[3] + p[1] * q[2] - p[2] * q[1] + p[3] * q[0]))


@njit(cache=True, error_model="numpy")
def quat_exp_nb(phi):
    th = math.sqrt(phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2])
    s = 0.5 if th < 1e-12 else math.sin(0.5 * th) / th
    return np.array((math.cos(0.5 * th), s * phi[0], s * phi[1], s * phi[2]))


@njit(cache=True, error_model="numpy")
def quat_to_dcm_nb(q):
    w, x, y, z = q[0], q[1], q[2], q[3]
    s = 2.0 / (w * w + x * x + y * y + z * z)
    xx, yy, zz = s * x * x, s * y * y, s * z * z
    xy, xz, yz = s * x * y, s * x * z, s * y * z
    wx, wy, wz = s * w * x, s * w * y, s * w * z
    R = np.empty((3, 3))
    R[0, 0], R[0, 1], R[0, 2] = 1.0 - (yy + zz), xy - wz, xz + wy
    R[1, 0], R[1, 1], R[1, 2] = xy + wz, 1.0 - (xx + zz), yz - wx
    R[2, 0], R[2, 1], R[2, 2] = xz - wy, yz + wx, 1.0 - (xx + yy)
    return R
