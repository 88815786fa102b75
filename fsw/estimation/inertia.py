"""Inertia tensor from Euler's equations: regressors, linear solutions, shifts, checks and intervals.

Euler's equations about the centre of mass in body (= sensor) axes (physics-and-seeds.md §2):

    J ω̇ + ω × (J ω) = M

are linear in the six components of the symmetric tensor. With the parameter vector

    p = [Ixx, Iyy, Izz, Ixy, Ixz, Iyz]      (the tensor's entries: J = [[Ixx, Ixy, Ixz], [Ixy, Iyy, Iyz],
                                              [Ixz, Iyz, Izz]], so Ixy = −∫xy dm; the same order as the
                                              DEBRIS_INERTIA_ESTIMATE message)

one sample gives three equations Φ(ω̇, ω) p = M, with Φ the regressor of the cellular-rotation-slowdown
paper (its matrix is exactly :func:`euler_regressor`). Everything here is a pure function of arrays;
the output-error fit to the magnetometer samples is in :mod:`fsw.estimation.euler_fit`.

Methods (issue "Euler identification"):

1. sedelnikov2023 special case (sensor axes parallel to the principal axes): eq. 4/5, diagonal tensor,
   per sample a 3×3 linear system A(ω, ω̇)·(Ixx, Iyy, Izz) = M — :func:`solve_diagonal_per_sample`. The
   paper's printed closed form eq. 7 is wrong (it does not solve eq. 5); it is kept as
   :func:`diagonal_printed_eq7` only so that a test can show the disagreement.
2. Least squares over all samples, diagonal or full (:func:`least_squares`), biased when ω, ω̇ are
   noisy (errors in variables); :func:`total_least_squares` (classical TLS of the augmented matrix) and
   :func:`errors_in_variables` (gradient-weighted / first-order maximum likelihood for noise in ω and
   ω̇) remove most of that bias.
3. Torque-free: Φ p = 0 — the tensor up to scale is the null vector of the stacked regressor
   (:func:`null_space_shape`, SVD); the scale κ from a known impulse (:func:`kappa_from_impulse`,
   cellular paper eq. 17–19).
4. Parallel-axis (Huygens–Steiner) shifts in both named directions; principal moments and axes.
5. Confidence half-widths at β = 95 % and 99 % from a covariance (:func:`half_width`).
6. Physical checks: positive definite, triangle inequalities of the principal moments.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import optimize, stats

from .rotations import skew

#: Component names in parameter order (DEBRIS_INERTIA_ESTIMATE order).
COMPONENTS = ("Ixx", "Iyy", "Izz", "Ixy", "Ixz", "Iyz")
#: (row, column) of each parameter in the 3×3 tensor.
INDEX = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
#: Confidence probabilities β reported everywhere (the papers' β = 0.95 and 0.99).
BETAS = (0.95, 0.99)

FLAG_POSITIVE_DEFINITE = 1
FLAG_TRIANGLE = 2
FLAG_FULL_TENSOR = 4


# --- tensor <-> parameters -----------------------------------------------------------------------

def tensor(p: np.ndarray) -> np.ndarray:
    """3×3 symmetric tensor(s) (..., 3, 3) from p (..., 6) = [Ixx, Iyy, Izz, Ixy, Ixz, Iyz]."""
    p = np.asarray(p, dtype=float)
    if p.shape[-1] == 3:
        p = np.concatenate([p, np.zeros(p.shape[:-1] + (3,))], axis=-1)
    J = np.empty(p.shape[:-1] + (3, 3))
    for k, (i, j) in enumerate(INDEX):
        J[..., i, j] = J[..., j, i] = p[..., k]
    return J


def params(J: np.ndarray) -> np.ndarray:
    """p (..., 6) from symmetric tensor(s) (..., 3, 3) (the upper triangle is read)."""
    J = np.asarray(J, dtype=float)
    return np.stack([J[..., i, j] for i, j in INDEX], axis=-1)


# --- regressors ----------------------------------------------------------------------------------

def euler_regressor(omega: np.ndarray, omega_dot: np.ndarray) -> np.ndarray:
    """Φ(ω̇, ω) of shape (..., 3, 6) with Φ p = J ω̇ + ω × (J ω) (cellular-rotation-slowdown, Φ p = 0).

    Columns in the order of :data:`COMPONENTS`.
    """
    w = np.asarray(omega, dtype=float)
    a = np.asarray(omega_dot, dtype=float)
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    P = np.zeros(np.broadcast_shapes(w.shape, a.shape)[:-1] + (3, 6))
    P[..., 0, :] = np.stack([ax, -y * z, y * z, ay - x * z, az + x * y, y * y - z * z], axis=-1)
    P[..., 1, :] = np.stack([x * z, ay, -x * z, ax + y * z, z * z - x * x, az - x * y], axis=-1)
    P[..., 2, :] = np.stack([-x * y, x * y, az, x * x - y * y, ax - y * z, ay + x * z], axis=-1)
    return P


def diagonal_regressor(omega: np.ndarray, omega_dot: np.ndarray) -> np.ndarray:
    """A(ω, ω̇) (..., 3, 3) of sedelnikov2023 eq. 5: A·(Ixx, Iyy, Izz) = M for a diagonal tensor."""
    return euler_regressor(omega, omega_dot)[..., :3]


def euler_moment(J: np.ndarray, omega: np.ndarray, omega_dot: np.ndarray) -> np.ndarray:
    """M = J ω̇ + ω × (J ω) (..., 3): the moment that produces (ω, ω̇) — the forward model."""
    Jw = np.einsum("...ij,...j->...i", J, omega)
    return np.einsum("...ij,...j->...i", J, omega_dot) + np.cross(omega, Jw)


# --- method 1: the paper's special case ----------------------------------------------------------

def solve_diagonal_per_sample(omega: np.ndarray, omega_dot: np.ndarray, moment: np.ndarray,
                              rcond: float = 1e-9) -> np.ndarray:
    """(Ixx, Iyy, Izz) per sample (N, 3) from eq. 5 as a linear solve; NaN where A is singular.

    "Singular" means the smallest singular value of A is below ``rcond`` times its largest (e.g. a
    sample with ω̇ = 0 and ω along a principal axis carries no information).
    """
    A = diagonal_regressor(omega, omega_dot)
    M = np.broadcast_to(np.asarray(moment, dtype=float), A.shape[:-1])
    s = np.linalg.svd(A, compute_uv=False)
    ok = s[..., -1] > rcond * s[..., 0]
    out = np.full(A.shape[:-1], np.nan)
    if np.any(ok):
        out[ok] = np.linalg.solve(A[ok], M[ok][..., None])[..., 0]
    return out


def diagonal_printed_eq7(omega: np.ndarray, omega_dot: np.ndarray, moment: np.ndarray) -> np.ndarray:
    """sedelnikov2023 eq. 7 exactly as printed: (Ixx, Iyy, Izz) per sample (..., 3).

    WRONG — it does not solve eq. 5 (physics-and-seeds.md §4). Kept only for the test that shows it;
    use :func:`solve_diagonal_per_sample` or :func:`least_squares`.
    """
    w = np.asarray(omega, dtype=float)
    a = np.asarray(omega_dot, dtype=float)
    M = np.broadcast_to(np.asarray(moment, dtype=float), w.shape)
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    Mx, My, Mz = M[..., 0], M[..., 1], M[..., 2]
    den_y = ax * ay + x * y * z**2
    c = x * y**2 * z - x * y * ax
    with np.errstate(divide="ignore", invalid="ignore"):
        izz = ((Mz * ax + Mx * x * y - (My * ax - Mx * x * z) * c / den_y)
               / (ax * az + x * y**2 * z + c * (x * z * ax - x * y * z**2) / den_y))
        iyy = izz * (x * z * ax + x * y * z**2) / den_y + (My * ax - Mx * x * z) / den_y
        ixx = (Mx + y * z * iyy - y * z * izz) / ax
    return np.stack([ixx, iyy, izz], axis=-1)


# --- estimates with covariance ---------------------------------------------------------------------

def z_value(beta: float) -> float:
    """Two-sided normal quantile for confidence probability β (1.960 for 0.95, 2.576 for 0.99)."""
    return float(stats.norm.ppf(0.5 + 0.5 * beta))


def half_width(cov: np.ndarray, beta: float) -> np.ndarray:
    """Half-widths of the β confidence intervals of each parameter: z_β · √diag(cov)."""
    return z_value(beta) * np.sqrt(np.clip(np.diagonal(cov, axis1=-2, axis2=-1), 0.0, None))


@dataclass
class InertiaEstimate:
    """An inertia tensor estimate about the centre of mass in sensor axes, with its covariance.

    ``p`` (6,) in :data:`COMPONENTS` order; ``cov`` (6, 6) kg²·m⁴ (zero rows/columns for components
    that were not estimated, e.g. the products of inertia of a diagonal-only fit); ``full`` says whether
    the products of inertia were estimated.
    """

    p: np.ndarray
    cov: np.ndarray
    method: str
    samples_used: int
    full: bool = True
    extra: dict = field(default_factory=dict)

    @property
    def J(self) -> np.ndarray:
        return tensor(self.p)

    def half_width(self, beta: float) -> np.ndarray:
        return half_width(self.cov, beta)

    @property
    def ci95(self) -> np.ndarray:
        return self.half_width(0.95)

    @property
    def ci99(self) -> np.ndarray:
        return self.half_width(0.99)

    @property
    def principal(self) -> np.ndarray:
        return principal_axes(self.J)[0]

    def checks(self) -> dict:
        return physical_checks(self.J)

    @property
    def flags(self) -> int:
        """DEBRIS_INERTIA_ESTIMATE flags: bit 0 positive definite, bit 1 triangle, bit 2 full tensor."""
        c = self.checks()
        return ((FLAG_POSITIVE_DEFINITE if c["positive_definite"] else 0)
                | (FLAG_TRIANGLE if c["triangle"] else 0) | (FLAG_FULL_TENSOR if self.full else 0))

    def to_json(self) -> dict:
        """The inertia JSON of recording-format.md (plus ci99, the checks and any extras)."""
        J = self.J
        c = self.checks()
        return {"frame": "sensor", "about": "centre_of_mass",
                "I_kgm2": J.tolist(), "ci95_kgm2": tensor(self.ci95).tolist(),
                "ci99_kgm2": tensor(self.ci99).tolist(),
                "principal_kgm2": [float(v) for v in c["principal_kgm2"]],
                "method": self.method, "samples_used": int(self.samples_used),
                "full_tensor": bool(self.full),
                "checks": {"positive_definite": c["positive_definite"], "triangle": c["triangle"],
                           "triangle_margin_kgm2": c["triangle_margin_kgm2"]},
                **self.extra}


def _stack(omega, omega_dot, moment, full: bool) -> tuple[np.ndarray, np.ndarray]:
    P = euler_regressor(omega, omega_dot)
    if not full:
        P = P[..., :3]
    M = np.broadcast_to(np.asarray(moment, dtype=float), P.shape[:-1])
    return P.reshape(-1, P.shape[-1]), M.reshape(-1)


def _embed(x: np.ndarray, cov: np.ndarray, full: bool) -> tuple[np.ndarray, np.ndarray]:
    if full:
        return x, cov
    p = np.zeros(6)
    p[:3] = x
    c = np.zeros((6, 6))
    c[:3, :3] = cov
    return p, c


def least_squares(omega: np.ndarray, omega_dot: np.ndarray, moment: np.ndarray, *,
                  full: bool = True) -> InertiaEstimate:
    """Ordinary least squares of Φ p = M over all samples (diagonal: ``full=False``, eq. 5 stacked).

    Covariance s²(ΦᵀΦ)⁻¹ with s² the residual variance. Unbiased only when ω and ω̇ are exact: with
    noisy rates the regressor is noisy and the estimate shrinks (errors in variables) — see
    :func:`total_least_squares` and :func:`errors_in_variables`.
    """
    A, b = _stack(omega, omega_dot, moment, full)
    x, *_ = np.linalg.lstsq(A, b, rcond=None)
    dof = max(A.shape[0] - A.shape[1], 1)
    s2 = float(np.sum((A @ x - b) ** 2)) / dof
    cov = s2 * np.linalg.pinv(A.T @ A)
    p, c = _embed(x, cov, full)
    return InertiaEstimate(p, c, "least squares" + ("" if full else " (diagonal)"), len(A) // 3, full)


def tls_solve(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Classical total least squares (Golub & Van Loan): min ‖[ΔA Δb]‖_F with (A+ΔA)x = b+Δb.

    x = −v[:n]/v[n] for v the right singular vector of [A b] with the smallest singular value.
    Consistent when the errors of all columns are independent with equal variance (scale the columns
    first otherwise).
    """
    C = np.column_stack([A, b])
    v = np.linalg.svd(C, full_matrices=False)[2][-1]
    if abs(v[-1]) < 1e-14 * np.abs(v).max():
        raise np.linalg.LinAlgError("TLS has no solution: the right-hand side is in the noise subspace")
    return -v[:-1] / v[-1]


def total_least_squares(omega: np.ndarray, omega_dot: np.ndarray, moment: np.ndarray, *,
                        full: bool = True, column_scale: np.ndarray | None = None) -> InertiaEstimate:
    """Total least squares of Φ p = M: the regressor is treated as noisy like the right-hand side.

    ``column_scale`` (n + 1,) divides the columns of [Φ M] so that their errors have comparable size
    (default: each column's RMS). The covariance reported is the first-order one of ordinary least
    squares at the TLS solution (a fair width, not an exact TLS covariance).
    """
    A, b = _stack(omega, omega_dot, moment, full)
    C = np.column_stack([A, b])
    s = np.sqrt(np.mean(C**2, axis=0)) if column_scale is None else np.asarray(column_scale, float)
    s = np.where(s > 0, s, 1.0)
    y = tls_solve(A / s[:-1], b / s[-1])
    x = y * s[-1] / s[:-1]
    dof = max(A.shape[0] - A.shape[1], 1)
    s2 = float(np.sum((A @ x - b) ** 2)) / dof
    cov = s2 * np.linalg.pinv(A.T @ A)
    p, c = _embed(x, cov, full)
    return InertiaEstimate(p, c, "total least squares" + ("" if full else " (diagonal)"), len(A) // 3, full)


def errors_in_variables(omega: np.ndarray, omega_dot: np.ndarray, moment: np.ndarray, *,
                        sigma_omega: float | np.ndarray, sigma_omega_dot: float | np.ndarray,
                        full: bool = True, p0: np.ndarray | None = None) -> InertiaEstimate:
    """Errors-in-variables fit of Euler's equations with noisy ω and ω̇ (white, per-axis 1-σ given).

    Minimises Σ_k r_kᵀ C_k(p)⁻¹ r_k with r_k = J ω̇_k + ω_k × J ω_k − M_k and C_k the first-order
    covariance of r_k from the noise of ω_k and ω̇_k:

        ∂r/∂ω̇ = J,   ∂r/∂ω = [ω]ₓ J − [J ω]ₓ,   C = J Σ_ω̇ Jᵀ + (∂r/∂ω) Σ_ω (∂r/∂ω)ᵀ

    (gradient-weighted least squares, the first-order maximum-likelihood estimator for an implicit
    model; a structured generalisation of total least squares). Started from ordinary least squares
    unless ``p0`` is given. Covariance from the Jacobian at the solution.
    """
    w = np.asarray(omega, dtype=float).reshape(-1, 3)
    a = np.asarray(omega_dot, dtype=float).reshape(-1, 3)
    M = np.broadcast_to(np.asarray(moment, dtype=float), w.shape).reshape(-1, 3)
    s_w = np.broadcast_to(np.asarray(sigma_omega, dtype=float), (3,))
    s_a = np.broadcast_to(np.asarray(sigma_omega_dot, dtype=float), (3,))
    if p0 is None:
        p0 = least_squares(w, a, M, full=full).p
    p0 = np.asarray(p0, dtype=float)
    x0 = p0 if full else p0[:3]
    scale = np.abs(x0[:3]).mean()
    W2, A2 = np.diag(s_w**2), np.diag(s_a**2)

    def whitened(x: np.ndarray) -> np.ndarray:
        J = tensor(x * scale)
        r = euler_moment(J, w, a) - M
        G = skew(w) @ J - skew(w @ J)      # J symmetric: J ω = ω J
        C = J @ A2 @ J + G @ W2 @ G.swapaxes(-1, -2)
        L = np.linalg.cholesky(C + 1e-30 * np.eye(3))
        return np.linalg.solve(L, r[..., None])[..., 0].ravel()

    sol = optimize.least_squares(whitened, x0 / scale, method="lm", xtol=1e-12, ftol=1e-12)
    x = sol.x * scale
    Jac = sol.jac / scale
    dof = max(sol.fun.size - x.size, 1)
    s2 = float(sol.fun @ sol.fun) / dof   # ≈ 1 when the noise levels given are right
    cov = max(s2, 1.0) * np.linalg.pinv(Jac.T @ Jac)
    p, c = _embed(x, cov, full)
    return InertiaEstimate(p, c, "errors-in-variables (gradient-weighted)" + ("" if full else " (diagonal)"),
                           len(w), full, extra={"chi2_per_dof": s2})


# --- method 3: torque-free null space and the scale from an impulse -----------------------------

def null_space_shape(omega: np.ndarray, omega_dot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Torque-free Φ p = 0: the unit null vector p_n of the stacked regressor (cellular paper eq. 11–13).

    Returns (p_n, singular values of the stack, ascending). p_n has the sign that makes trace > 0.
    The tensor is κ · tensor(p_n) for an unknown κ > 0 (:func:`kappa_from_impulse`). A clear gap
    between the two smallest singular values means the motion was rich enough to fix the shape.
    """
    A, _ = _stack(omega, omega_dot, np.zeros(3), True)
    _, s, Vt = np.linalg.svd(A, full_matrices=False)
    p = Vt[-1]
    if p[:3].sum() < 0:
        p = -p
    return p / np.linalg.norm(p), s[::-1]


def kappa_from_impulse(p_n: np.ndarray, omega_1: np.ndarray, omega_2: np.ndarray, moment: np.ndarray,
                       tau_s: float, interval_s: float | None = None) -> float:
    """Scale κ of the tensor κ·tensor(p_n) from a known impulse (cellular paper eq. 17–19).

    Integrating Euler's equations over an interval T that holds the impulse (M for τ seconds; rate ω₁
    at its start, ω₂ at its end; T = τ by default) with the trapezoid rule for the gyroscopic term:

        κ · j = M τ,   j = J_n (ω₂ − ω₁) + [ω₂ × J_n ω₂ + ω₁ × J_n ω₁] T / 2

    solved in least squares (κ = j·Mτ / |j|²). Accurate for an interval short against the rotation
    (the paper: τ = 1 s); for long pulses fit the scale with the dynamics (output-error).
    """
    Jn = tensor(p_n)
    T = tau_s if interval_s is None else interval_s
    w1, w2 = np.asarray(omega_1, float), np.asarray(omega_2, float)
    j = Jn @ (w2 - w1) + 0.5 * T * (np.cross(w2, Jn @ w2) + np.cross(w1, Jn @ w1))
    mt = np.asarray(moment, float) * tau_s
    return float(j @ mt / (j @ j))


# --- method 4: parallel axes, principal axes -----------------------------------------------------

def steiner_term(mass_kg: float, d_m: np.ndarray) -> np.ndarray:
    """m(|d|² E − d dᵀ): what the parallel-axis theorem adds going away from the centre of mass."""
    d = np.asarray(d_m, dtype=float)
    return mass_kg * (float(d @ d) * np.eye(3) - np.outer(d, d))


def tensor_about_point_from_com(J_com: np.ndarray, mass_kg: float, d_m: np.ndarray) -> np.ndarray:
    """Centre of mass → point P: J_P = J_C + m(|d|²E − ddᵀ), d = r_P − r_C (axes parallel).

    This is the direction sedelnikov2023 eq. 8 actually applies (adding m·a² to Iyy and Izz for an
    offset a along x), although the paper means to go to the centre of mass.
    """
    return np.asarray(J_com, dtype=float) + steiner_term(mass_kg, d_m)


def tensor_about_com_from_point(J_point: np.ndarray, mass_kg: float, d_m: np.ndarray) -> np.ndarray:
    """Point P → centre of mass: J_C = J_P − m(|d|²E − ddᵀ), d = r_P − r_C (axes parallel).

    Euler's equations with the moment about the centre of mass already give J_C wherever the sensor
    sits; this shift is needed only for a tensor known about another point.
    """
    return np.asarray(J_point, dtype=float) - steiner_term(mass_kg, d_m)


def principal_axes(J: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Principal moments (ascending) and axes: columns of a right-handed rotation R, J = R diag(I) Rᵀ."""
    I, R = np.linalg.eigh(0.5 * (np.asarray(J, float) + np.asarray(J, float).T))
    if np.linalg.det(R) < 0:
        R[:, 2] = -R[:, 2]
    return I, R


def principal_ratios(J: np.ndarray) -> np.ndarray:
    """(I1/I3, I2/I3) of the ascending principal moments: the scale-free shape."""
    I = principal_axes(J)[0]
    return I[:2] / I[2]


def principal_ratios_cov(p: np.ndarray, cov_p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(I1/I3, I2/I3) of the tensor p (6,) and their covariance (2, 2) from the covariance of p.

    First order: dI_i/dJ = v_i v_iᵀ (v_i the unit principal axis; a product of inertia enters J twice),
    d(I_i/I3) = (dI_i − (I_i/I3) dI3)/I3. Valid while the principal moments are distinct by more than
    their uncertainty.
    """
    I, R = principal_axes(tensor(p))
    G = np.zeros((3, 6))
    for k, (a, b) in enumerate(INDEX):
        G[:, k] = R[a, :] * R[b, :] * (1.0 if a == b else 2.0)
    r = I[:2] / I[2]
    D = (G[:2] - np.outer(r, G[2])) / I[2]
    return r, D @ np.asarray(cov_p, float) @ D.T


# --- method 6: physical checks -------------------------------------------------------------------

def physical_checks(J: np.ndarray, rel_tol: float = 1e-9) -> dict:
    """Positive definiteness and the triangle inequalities I_i ≤ I_j + I_k of the principal moments.

    Reported, never enforced: an estimate that fails them says the data did not determine the tensor.
    ``triangle_margin_kgm2`` = I1 + I2 − I3 (ascending; ≥ 0 for a physical body).
    """
    I = principal_axes(J)[0]
    margin = float(I[0] + I[1] - I[2])
    return {"principal_kgm2": I, "positive_definite": bool(I[0] > 0),
            "triangle": bool(margin >= -rel_tol * abs(I[2])), "triangle_margin_kgm2": margin}


def relative_errors(p_est: np.ndarray, p_true: np.ndarray) -> np.ndarray:
    """Component errors relative to the largest principal moment of the truth (products of inertia
    can be zero, so they are scored against the tensor's size, as the targets are)."""
    return (np.asarray(p_est) - np.asarray(p_true)) / principal_axes(tensor(p_true))[0][-1]

