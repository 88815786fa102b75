"""Host-magnetics calibration: hard and soft iron from the field's magnitude along the orbit (TWOSTEP).

Model (Alonso & Shuster 2002, "Complete linear attitude-independent magnetometer calibration",
J. Astronaut. Sci. 50(4); the same convention)::

    B_meas = (I + D)⁻¹ B_true + b + ε        ⇔        B_true = (I + D) (B_meas − b)

`b` is the hard iron as the sensor sees it (sensor axes, T), `D` the soft iron, a symmetric 3×3
matrix (I + D positive definite), ε the sensor noise (σ per axis). A host whose truth is
``B_meas = S B_true + h`` has b = h and I + D = S⁻¹ when S is symmetric. Only the field's magnitude is
used (attitude-independent), so a rotation is not observable: a non-symmetric S = R P (polar
decomposition) is recovered as I + D = P⁻¹ and its rotation R stays in the data, as a mounting
misalignment would. Applied to a sample: :func:`apply`, B_true ≈ (I + D)(B_meas − b).

The estimate. With E = (I + D)² − I, c = (I + E) b and z = |B_meas|² − |B_model|²::

    z = 2 B_measᵀ c − B_measᵀ E B_meas − μ + v,     μ = bᵀ(I + E) b − σ² tr(I + E)

is linear in φ = (c, E's 6 unique terms, μ) (the σ² term is the mean of the noise's square), with
noise v of variance σ_z² ≈ 4 |B_model|² (σ² + σ_model²) (σ_model: the field model's error in
magnitude). Step one (centred, the constraint on μ dropped): the weighted linear least squares in φ,
from which b and D follow (√ of I + E by its eigen-decomposition). Step two: Gauss–Newton (Fisher
scoring) on θ = (b, D's 6 unique terms) with μ tied to them. Both steps need the data only through
its sufficient statistics N = Σ w a aᵀ (10×10), y = Σ w a z, Σ w z² (w = 1/σ_z²): the flight form
accumulates them sample by sample (O(100) operations, optionally with exponential forgetting of time
constant `memory_s`) and solves from time to time; nothing grows with the number of samples. The Fisher
information of θ is F = Gᵀ N G (G = ∂φ/∂θ); its inverse is the covariance.

The hard iron's thermal drift. The host's iron warms and cools once per orbit (sun and eclipse): b moves
by ~1 µT. A constant b leaves that (~0.4 µT RMS) and, on a quiet chip, refuses the later minutes as
misfits. The flight form models it as the first harmonic of the orbit's period P::

    b(t) = b + β_c cos ωt + β_s sin ωt,        ω = 2π / P

which stays linear in φ: c(t) = M b(t) splits into c, c_c = M β_c, c_s = M β_s (regressors 2B, 2B cos ωt,
2B sin ωt), μ(t) = b(t)ᵀ M b(t) into μ = bᵀMb + ½ Σ β_kᵀMβ_k, μ_c = 2bᵀMβ_c, μ_s = 2bᵀMβ_s (its second
harmonic, ~|β|² ≈ 1 µT², against σ_z of tens of µT², left out). The sums gain the products with cos ωt
and sin ωt (exact, so the noise adjustment is unchanged); θ gains β_c, β_s, with a prior of σ `DRIFT_T`
(1 µT) per axis — what a thermal cycle does, and what keeps the first minutes (where cos ωt ≈ 1 cannot
be told from the constant) well posed. What is published and applied is b(t) at the solution's time
with the covariance of b(t) (J C Jᵀ: what the drift's terms leave unknown included), and its rate
db/dt, with which the applied hard iron follows the drift between solutions. A random walk of b
(process noise) was the other candidate: to follow 1 µT per orbit it must forget b's information
within minutes, so its σ of b stays at ~0.2 µT with a 1.5 µT sensor (~0.07 µT with the isoi chip) and
never reaches the σ goal; the harmonic keeps all the information and costs three parameters per axis
(bench.calibration, 20 hosts at 1.5 µT and 5 Hz: the σ goals reached after a median 2,640 s instead of
1,260 s for a constant host, 19 of 20 hosts within the orbit either way). The cost of a real
thermal cycle that is not a pure sine: its higher harmonics stay in the residual. A sudden jump of b is
not drift: it is flagged, then learned again (:meth:`MagCal.solve`).

Checks before a solution is published as good (:func:`check`): the Gauss–Newton iteration converged
and I + D is positive definite; the normalised Fisher matrix is well conditioned (a body that sees one
direction only gives a singular one); the residual's χ² per degree of freedom is plausible; the change
from the last good calibration is within bounds; each σ below its goal (then `converged`). Anything
else keeps the last good calibration and says why (`state`).

Units: interfaces in tesla and seconds; inside, µT (well-scaled numbers).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from .magcal_stats import (N_PHI, N_THETA, Stats, accumulate, contribution, n_phi, n_theta, normal_equations,
                           trig)

UT_PER_T = 1e6
#: D's unique terms, in this order (also the order of the telemetry and the covariance)
D_TERMS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))

# states of a calibration (DEBRIS_MAGCAL_STATE in the dialect has the same values)
NO_FIELD = 0        #: no field model along the orbit on board: inactive, samples pass uncorrected
COLLECTING = 1      #: too few samples yet
CONVERGED = 2       #: the published calibration is good and each σ is below its goal
UNCERTAIN = 3       #: good but not yet within the σ goals (applied: better than none)
REJECTED = 4        #: the latest solution failed a check: the last good one stays (if any)
#: `MagCal.restored` (DEBRIS_MAGCAL's `restored`): the applied calibration is not one restored after a restart,
#: is one (not yet confirmed by a solution from new samples), or one was and the new samples refused it
NOT_RESTORED, RESTORED, RESTORED_DROPPED = 0, 1, 2
STATE_NAMES = {NO_FIELD: "no field on board", COLLECTING: "collecting", CONVERGED: "converged",
               UNCERTAIN: "uncertain", REJECTED: "rejected"}


#: the hard iron's thermal drift the flight form follows: a cycle per orbit (the period of a low orbit,
#: 480–550 km; the loop's calibration step gives the orbit's own when it knows it), its amplitude per axis
#: the prior's σ of its terms
DRIFT_PERIOD_S = 5670.0
DRIFT_T = 1e-6

#: what the calibration against the onboard model cannot explain, taken as noise on |B| beside the
#: sensor's: the model's error (IGRF-14 degree 8: 0.07 µT RMS), what the drift's first harmonic leaves of a
#: real thermal cycle. Without it a quiet chip (0.05 µT) refuses later minutes as misfits of a good
#: calibration; with the drift followed, it makes σ of b conservative on such a chip (errors ~0.2 σ).
MODEL_SIGMA_T = 0.3e-6

@dataclass(frozen=True)
class Calibration:
    """A hard/soft iron calibration: B_true = (I + D)(B_meas − b); `cov` the 9×9 covariance of
    (b [T], D's `D_TERMS`) in those units."""

    b_T: np.ndarray = field(default_factory=lambda: np.zeros(3))
    D: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    cov: np.ndarray | None = None

    @property
    def sigma(self) -> np.ndarray:
        """1-σ of (b [T] (3), D's `D_TERMS` (6)); infinite without a covariance."""
        if self.cov is None:
            return np.full(N_THETA, np.inf)
        return np.sqrt(np.clip(np.diag(self.cov), 0.0, None))

    def to_json(self) -> dict:
        """The calibration file's content (see `from_json`)."""
        return {"hard_iron_uT": (self.b_T * UT_PER_T).tolist(), "soft_iron": self.D.tolist(),
                "sigma": None if self.cov is None else
                {"hard_iron_uT": (self.sigma[:3] * UT_PER_T).tolist(), "soft_iron_terms": self.sigma[3:].tolist()},
                "model": "B_true = (I + soft_iron) (B_meas - hard_iron)"}

    @classmethod
    def from_json(cls, d: dict) -> "Calibration":
        """From ``{"hard_iron_uT": [3 numbers], "soft_iron": [[3×3 symmetric]]}`` (more keys ignored).
        ValueError when it is not one (wrong shapes, not finite, not symmetric, I + D not positive
        definite)."""
        if not isinstance(d, dict):
            raise ValueError("a calibration is a JSON object with hard_iron_uT and soft_iron")
        try:
            b = np.asarray(d["hard_iron_uT"], float) / UT_PER_T
            D = np.asarray(d.get("soft_iron", np.zeros((3, 3))), float)
        except KeyError as e:
            raise ValueError(f"calibration has no {e.args[0]}") from None
        except (TypeError, ValueError):
            raise ValueError("calibration values must be numbers") from None
        if b.shape != (3,) or D.shape != (3, 3):
            raise ValueError("hard_iron_uT must be 3 numbers and soft_iron a 3x3 matrix")
        if not (np.all(np.isfinite(b)) and np.all(np.isfinite(D))):
            raise ValueError("calibration values must be finite")
        if not np.allclose(D, D.T, atol=1e-9):
            raise ValueError("soft_iron must be symmetric")
        if np.min(np.linalg.eigvalsh(np.eye(3) + D)) <= 0.05:
            raise ValueError("I + soft_iron must be positive definite (eigenvalues above 0.05)")
        return cls(b, D)


IDENTITY = Calibration()


def apply(cal: Calibration, b_meas_T: np.ndarray) -> np.ndarray:
    """B_true ≈ (I + D)(B_meas − b), for one sample (3,) or many (n, 3)."""
    return (np.asarray(b_meas_T, float) - cal.b_T) @ (np.eye(3) + cal.D).T


# --- the two steps --------------------------------------------------------------------------------------

def _sym(d6: np.ndarray) -> np.ndarray:
    D = np.empty((3, 3))
    for k, (i, j) in enumerate(D_TERMS):
        D[i, j] = D[j, i] = d6[k]
    return D


def _unique(M: np.ndarray) -> np.ndarray:
    return np.array([M[i, j] for i, j in D_TERMS])


_E_UNIT = tuple(np.array([[1.0 if {(r, c), (c, r)} & {(i, j)} else 0.0 for c in range(3)] for r in range(3)])
                for i, j in D_TERMS)


def phi_of_theta(theta: np.ndarray, jacobian: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """φ(θ) and G = ∂φ/∂θ; θ = (b [µT], D's unique terms, β_k [µT] for each harmonic term); with the
    hard iron b(t) = b + Σ_k τ_k(t) β_k and M = (I + D)²: c = M b, E = M − I, μ = bᵀM b + ½ Σ β_kᵀ M β_k
    (the mean over the orbit of b(t)ᵀ M b(t); its second harmonic, ~|β|², is left out), c_k = M β_k,
    μ_k = 2 bᵀ M β_k (the noise's mean square is taken out of the adjusted statistics)."""
    theta = np.asarray(theta, float)
    nb = (len(theta) - N_THETA) // 3
    b, ID = theta[:3], np.eye(3) + _sym(theta[3:9])
    betas = [theta[N_THETA + 3 * k:N_THETA + 3 * k + 3] for k in range(nb)]
    M = ID @ ID
    Mb = M @ b
    phi = [Mb, _unique(M - np.eye(3)), [b @ Mb + 0.5 * sum(be @ M @ be for be in betas)]]
    for be in betas:
        phi += [M @ be, [2.0 * Mb @ be]]
    phi = np.concatenate(phi)
    if not jacobian:
        return phi, None
    G = np.zeros((len(phi), len(theta)))
    G[:3, :3] = M
    G[9, :3] = 2 * Mb
    for k, Ek in enumerate(_E_UNIT):
        dM = Ek @ ID + ID @ Ek
        G[:3, 3 + k] = dM @ b
        G[3:9, 3 + k] = _unique(dM)
        G[9, 3 + k] = b @ dM @ b + 0.5 * sum(be @ dM @ be for be in betas)
        for q, be in enumerate(betas):
            r = N_PHI + 4 * q
            G[r:r + 3, 3 + k] = dM @ be
            G[r + 3, 3 + k] = 2.0 * b @ dM @ be
    for q, be in enumerate(betas):
        r, c = N_PHI + 4 * q, N_THETA + 3 * q
        G[9, c:c + 3] = M @ be
        G[r:r + 3, c:c + 3] = M
        G[r + 3, c:c + 3] = 2 * Mb
        G[r + 3, :3] = 2 * M @ be
    return phi, G


def cost(N: np.ndarray, y: np.ndarray, zz: float, phi: np.ndarray) -> float:
    """Σ w (z − aᵀφ)² from the normal equations."""
    return float(zz - 2 * phi @ y + phi @ N @ phi)


def _prior(n: int, drift_uT: float | None) -> np.ndarray:
    """The prior information (diagonal) on θ: none on b and D, 1/drift² on each β_k's terms."""
    p = np.zeros(n)
    if n > N_THETA and drift_uT:
        p[N_THETA:] = 1.0 / drift_uT ** 2
    return p


def centred_estimate(st: Stats, drift_uT: float | None = None) -> np.ndarray | None:
    """Step one: θ from the unconstrained linear fit (μ free; the drift's terms c_k held near 0 by the
    prior), or None when it has no valid solution (singular, or I + E not positive definite)."""
    N, y, _ = normal_equations(st)
    nph = len(y)
    ridge = np.zeros(nph)
    for q in range((nph - N_PHI) // 4):
        ridge[N_PHI + 4 * q:N_PHI + 4 * q + 3] = _prior(N_THETA + 3, drift_uT)[N_THETA:]
    try:
        phi = np.linalg.solve(N + np.diag(ridge), y)
    except np.linalg.LinAlgError:
        return None
    M = np.eye(3) + _sym(phi[3:9])
    ev, V = np.linalg.eigh(M)
    if not np.all(np.isfinite(ev)) or ev.min() <= 0.0:
        return None
    ID = (V * np.sqrt(ev)) @ V.T
    out = [np.linalg.solve(M, phi[:3]), _unique(ID - np.eye(3))]
    for q in range((nph - N_PHI) // 4):
        out.append(np.linalg.solve(M, phi[N_PHI + 4 * q:N_PHI + 4 * q + 3]))
    return np.concatenate(out)


@dataclass(frozen=True)
class Prior:
    """What was known of p = A θ before these samples (a calibration restored with its covariance):
    the cost (A θ − m)ᵀ L (A θ − m) added to the fit's, µT units (see :func:`current` for A)."""

    A: np.ndarray   #: (9, len θ)
    m: np.ndarray   #: (9,)
    L: np.ndarray   #: (9, 9) information


@dataclass(frozen=True)
class Solution:
    theta: np.ndarray        #: (b [µT], D's unique terms, β_k [µT])
    fisher: np.ndarray       #: in those units, the prior on β_k included
    chi2_dof: float          #: the raw residual's χ² per degree of freedom
    iterations: int
    converged: bool          #: the Gauss–Newton step became negligible


def refine(st: Stats, theta0: np.ndarray, max_iter: int = 20, tol: float = 1e-6,
           drift_uT: float | None = None, prior: Prior | None = None) -> Solution:
    """Step two: Gauss–Newton (Fisher scoring) on θ from `theta0` over the adjusted statistics (plus the
    prior on the drift's terms, of σ `drift_uT`, and `prior`), the step halved while it does not lower
    the cost."""
    N, y, zz = normal_equations(st)
    theta = np.array(theta0, float)
    lam = _prior(len(theta), drift_uT)
    F_prior = np.diag(lam)
    if prior is not None:
        F_prior = F_prior + prior.A.T @ prior.L @ prior.A

    def total(phi, th):
        c = cost(N, y, zz, phi) + float(np.sum(lam * th * th))
        if prior is not None:
            r = prior.A @ th - prior.m
            c += float(r @ prior.L @ r)
        return c

    def prior_gradient(th):
        g = -lam * th
        if prior is not None:
            g = g - prior.A.T @ (prior.L @ (prior.A @ th - prior.m))
        return g

    phi, G = phi_of_theta(theta)
    c = total(phi, theta)
    done = False
    it = 0
    while it < max_iter:
        it += 1
        F = G.T @ N @ G + F_prior
        g = G.T @ (y - N @ phi) + prior_gradient(theta)
        try:
            step = np.linalg.solve(F, g)
        except np.linalg.LinAlgError:
            break
        for _ in range(30):
            cand = theta + step
            phi_c, _ = phi_of_theta(cand, jacobian=False)
            c_c = total(phi_c, cand)
            if c_c <= c or not np.isfinite(c):
                break
            step = 0.5 * step
        else:
            break
        theta, c = cand, c_c
        phi, G = phi_of_theta(theta)
        # converged when the step is small against its own σ
        if float(step @ F @ step) < tol:
            done = True
            break
    F = G.T @ N @ G + F_prior
    dof = max(st.weight - len(theta), 1.0)
    raw = cost(*normal_equations(st, raw=True), phi)
    return Solution(theta, F, max(raw, 0.0) / dof, it, done)


def current(theta: np.ndarray, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(p, J): what is applied at the time of `tau` — p = (b(t) = b + Σ τ_k β_k, D's terms) (9) — and
    J = ∂p/∂θ."""
    theta = np.asarray(theta, float)
    J = np.zeros((N_THETA, len(theta)))
    J[:, :N_THETA] = np.eye(N_THETA)
    for q in range((len(theta) - N_THETA) // 3):
        J[:3, N_THETA + 3 * q:N_THETA + 3 * q + 3] = tau[q + 1] * np.eye(3)
    return J @ theta, J


def rate(theta: np.ndarray, t_s: float, period_s: float | None) -> np.ndarray:
    """db/dt [µT/s] of the hard iron at `t_s` (0 for a constant host)."""
    if period_s is None or len(theta) <= N_THETA:
        return np.zeros(3)
    w = 2.0 * math.pi / period_s
    a = w * t_s
    return w * (-math.sin(a) * theta[9:12] + math.cos(a) * theta[12:15])


# --- the checks ------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Limits:
    """What a solution must pass (µT where a field)."""

    #: of the Fisher matrix normalised by its diagonal: a sphere of directions well covered gives 3–5;
    #: above ~30 the quadratic model's bias from the noise is several σ (bench.calibration)
    max_condition: float = 25.0
    max_chi2_dof: float = 4.0        #: residual χ² per degree of freedom, all samples
    #: residual χ² per sample of the samples since the last solution (a bad stretch, diluted in the
    #: sums of a whole orbit, shows there)
    max_window_chi2: float = 3.0
    max_hard_iron_uT: float = 300.0  #: plausibility of |b| per axis
    max_soft_iron: float = 0.4       #: |eigenvalue of D|
    #: plausibility of the drift's amplitude per axis (a thermal cycle moves the hard iron by ~1 µT)
    max_drift_uT: float = 10.0
    #: change from the last good calibration refused when above both this (b per axis, µT; D's terms)
    #: and `max_change_sigmas` of the σ of the difference (the last good one's and this one's) ...
    max_change_uT: float = 1.0
    max_change_soft: float = 0.01
    max_change_sigmas: float = 5.0
    #: ... unless that many successive solutions in a row insist on it (the host really changed)
    confirm_change_after: int = 3
    #: stretches in a row that do not fit the last good calibration before the sums start again
    restart_after: int = 10
    goal_sigma_uT: float = 0.1       #: σ of b per axis for `converged`
    goal_sigma_soft: float = 0.002   #: σ of D's terms for `converged`


CHANGE_TOO_LARGE = "change from the last good calibration too large"
WINDOW_RESIDUAL = "residual of the latest samples too large"


def window_chi2(recent: Stats, theta: np.ndarray) -> float:
    """χ² per sample of `recent`'s samples under θ."""
    return cost(*normal_equations(recent, raw=True), phi_of_theta(theta, jacobian=False)[0]) / max(recent.weight, 1e-12)


def normalised_condition(F: np.ndarray) -> float:
    d = np.diag(F)
    if not np.all(np.isfinite(F)) or np.any(d <= 0):
        return math.inf
    s = 1.0 / np.sqrt(d)
    return float(np.linalg.cond(F * s[:, None] * s[None, :]))


def check(sol: Solution, last_good: np.ndarray | None, lim: Limits, last_sigma: np.ndarray | None = None,
          insisted: int = 0, recent: Stats | None = None,
          tau: np.ndarray | None = None) -> tuple[str | None, np.ndarray | None]:
    """(None, covariance) when `sol` may be published, else (why not, None). The covariance (9×9) is that
    of p = (b(t), D's terms) at the time of `tau` (the latest sample's; None: a constant host), from the
    inverse Fisher matrix scaled by the residual's χ²/dof when that is above 1 (σ_z is approximate); the
    conditioning is judged on its inverse. `last_good`: the last published p; `last_sigma`: its σ (µT
    units); `insisted`: how many solutions in a row were refused for their change already; `recent`: the
    samples since the last solution."""
    th = sol.theta
    if not sol.converged or not np.all(np.isfinite(th)):
        return "did not converge", None
    p, J = current(th, np.ones(1) if tau is None else tau)
    try:
        cov_all = np.linalg.inv(sol.fisher) * max(1.0, sol.chi2_dof)
        cov = J @ cov_all @ J.T
        cond = normalised_condition(np.linalg.inv(cov))
    except np.linalg.LinAlgError:
        cond = math.inf
    if cond > lim.max_condition:
        return f"ill-conditioned (Fisher condition {cond:.3g})", None
    if np.any(np.diag(cov) <= 0):
        return "ill-conditioned (covariance not positive)", None
    if sol.chi2_dof > lim.max_chi2_dof:
        return f"residual too large (chi2/dof {sol.chi2_dof:.3g})", None
    if recent is not None and recent.n > 0:
        chi2 = window_chi2(recent, th)
        if chi2 > lim.max_window_chi2:
            return f"{WINDOW_RESIDUAL} (chi2/sample {chi2:.3g})", None
    ev = np.linalg.eigvalsh(_sym(th[3:9]))
    if (np.max(np.abs(th[:3])) > lim.max_hard_iron_uT or np.max(np.abs(ev)) > lim.max_soft_iron
            or (len(th) > N_THETA and np.max(np.abs(th[N_THETA:])) > lim.max_drift_uT)):
        return "implausible values", None
    if last_good is not None and insisted < lim.confirm_change_after:
        bound = np.array([lim.max_change_uT] * 3 + [lim.max_change_soft] * 6)
        if last_sigma is not None:
            both = np.sqrt(last_sigma ** 2 + np.diag(cov))
            bound = np.maximum(bound, lim.max_change_sigmas * both)
        if np.any(np.abs(p - last_good) > bound):
            return CHANGE_TOO_LARGE, None
    return None, cov


_UT_SCALE = np.array([UT_PER_T] * 3 + [1.0] * 6)


def to_calibration(theta: np.ndarray, cov_uT: np.ndarray | None, tau: np.ndarray | None = None) -> Calibration:
    """θ (µT) and the covariance of p (µT units, see :func:`check`) to a :class:`Calibration` (T) at the
    time of `tau` (None: a constant host)."""
    p, _ = current(theta, np.ones(1) if tau is None else tau)
    cov = None if cov_uT is None else cov_uT / _UT_SCALE[:, None] / _UT_SCALE[None, :]
    return Calibration(p[:3] / UT_PER_T, _sym(p[3:]), cov)


def estimate(b_meas_T: np.ndarray, b_model_T: np.ndarray, sigma_T: float, sigma_model_T: float = 0.0,
             limits: Limits = Limits()) -> tuple[Calibration | None, str | None, Solution | None]:
    """Batch TWOSTEP (a constant host) on samples (n, 3) and the model's magnitudes (n,): (calibration,
    None, solution) when it passes :func:`check`, else (None, why, solution or None)."""
    st = accumulate(Stats(), np.asarray(b_meas_T) * UT_PER_T, np.asarray(b_model_T) * UT_PER_T,
                    sigma_T * UT_PER_T, sigma_model_T * UT_PER_T)
    return _solve(st, None, limits)


def _solve(st: Stats, last_good: np.ndarray | None, lim: Limits,
           last_sigma: np.ndarray | None = None, insisted: int = 0, recent: Stats | None = None,
           tau: np.ndarray | None = None, drift_uT: float | None = None, theta_good: np.ndarray | None = None,
           prior: Prior | None = None):
    if st.n < 2 * n_phi(st.n_tau):
        return None, "too few samples", None
    theta0 = centred_estimate(st, drift_uT)
    starts = [t for t in (theta0, theta_good, np.zeros(n_theta(st.n_tau))) if t is not None]
    sol = None
    for t0 in starts:
        # a prior slows Fisher scoring to a linear rate along what the few new samples hardly see
        sol = refine(st, t0, max_iter=20 if prior is None else 80, drift_uT=drift_uT, prior=prior)
        if sol.converged:
            break
    why, cov = check(sol, last_good, lim, last_sigma, insisted, recent, tau)
    if why:
        return None, why, sol
    return to_calibration(sol.theta, cov, tau), None, sol


# --- the flight form ------------------------------------------------------------------------------------

class MagCal:
    """Recursive TWOSTEP: :meth:`update` with each sample (B_meas [T], |B_model| [T], t [s]); every
    `solve_every_s` of sample time the statistics are solved and the result checked. `calibration` is
    the last good one (identity before any) with the hard iron at the time of that solution, `state`
    says where it stands, `reason` why the latest solution was refused. `memory_s`: time constant of the
    exponential forgetting (None: none).

    The hard iron's drift (`drift_period_s`, default `DRIFT_PERIOD_S`; None: a constant host): b(t) = b +
    β_c cos ωt + β_s sin ωt, ω = 2π / the period (the thermal cycle of the orbit), the β's with a prior of
    σ `drift_T` per axis (what a thermal cycle does; it also keeps the first minutes, where cos ωt ≈ 1 is
    confused with the constant, well posed). The published hard iron is b(t) at the solution's time, its
    covariance that of b(t) (what the drift's terms leave unknown included); :meth:`apply` with a time
    follows b(t) between solutions (at most two solution periods ahead)."""

    def __init__(self, sigma_T: float, *, sigma_model_T: float = 0.0, solve_every_s: float = 60.0,
                 min_samples: int = 200, memory_s: float | None = None,
                 drift_period_s: float | None = DRIFT_PERIOD_S, drift_T: float = DRIFT_T,
                 limits: Limits = Limits()) -> None:
        self.sigma_uT = sigma_T * UT_PER_T
        self.sigma_model_uT = sigma_model_T * UT_PER_T
        self.solve_every_s = solve_every_s
        self.min_samples = min_samples
        self.memory_s = memory_s
        if drift_period_s is not None and not (math.isfinite(drift_period_s) and drift_period_s > 0):
            raise ValueError(f"drift_period_s must be > 0 or None, got {drift_period_s!r}")
        self.drift_period_s = drift_period_s
        self.drift_uT = drift_T * UT_PER_T
        self.limits = limits
        self.reset()

    def reset(self) -> None:
        self.stats = Stats(self.n_tau)
        self.recent = Stats(self.n_tau)  # the samples since the last solution
        self.calibration = IDENTITY
        self._good: np.ndarray | None = None       # θ of the last good solution
        self._good_p: np.ndarray | None = None     # and what it published (b(t), D)
        self.state = COLLECTING
        self.reason: str | None = None
        self.chi2_dof = math.nan
        self.solves = 0
        #: calibrations published (applied) since the start: changes exactly when `calibration` does
        self.published = 0
        self.rejections = 0
        #: samples of refused stretches taken out of the sums; such stretches in a row; restarts
        self.dropped = 0
        self.misfits = 0
        self.restarts = 0
        #: sample times of the first calibration published, and of the first within the σ goals
        self.first_good_at_s: float | None = None
        self.converged_at_s: float | None = None
        #: the time of the published calibration's hard iron, and its rate there [T/s]
        self.published_at_s: float | None = None
        self.rate_T_per_s = np.zeros(3)
        self._t_last: float | None = None
        self._t_solve: float | None = None
        self._insisted = 0
        #: after a restart: the new sums are not judged against the last good calibration, which stays
        #: applied until a solution from them passes the checks
        self._relearning = False
        self.restored = NOT_RESTORED
        self.restored_dropped = 0
        #: what a calibration restored with its covariance knew (`Prior`), fused with the new samples
        #: until the host is found to have changed
        self.prior: Prior | None = None
        self._prior_weight = 1.0  # its information forgotten as the samples' is (`memory_s`)

    @property
    def n_tau(self) -> int:
        return 1 if self.drift_period_s is None else 3

    @property
    def samples(self) -> int:
        return self.stats.n

    @property
    def good(self) -> bool:
        """A calibration that passed the checks is being applied."""
        return self._good is not None

    def _tau(self, t_s: float) -> np.ndarray:
        return trig(t_s, self.drift_period_s)

    def update(self, b_meas_T: np.ndarray, b_model_mag_T: float, t_s: float) -> bool:
        """Add a sample; True when a new calibration was published."""
        if not (np.all(np.isfinite(b_meas_T)) and math.isfinite(b_model_mag_T) and b_model_mag_T > 0
                and math.isfinite(t_s)):
            return False
        forget = 1.0
        if self.memory_s is not None and self._t_last is not None:
            forget = math.exp(-max(t_s - self._t_last, 0.0) / self.memory_s)
        self._t_last = t_s
        c = contribution(np.asarray(b_meas_T) * UT_PER_T, b_model_mag_T * UT_PER_T, self.sigma_uT,
                         self.sigma_model_uT, None if self.n_tau == 1 else self._tau(t_s)[None])
        self.stats.add(c, forget)
        self.recent.add(c, forget)
        self._prior_weight *= forget
        if self._t_solve is None:
            self._t_solve = t_s
        if self.stats.n < self.min_samples or t_s - self._t_solve < self.solve_every_s:
            return False
        self._t_solve = t_s
        return self.solve(t_s)

    def solve(self, t_s: float) -> bool:
        """Solve the statistics now; True when the result was published. First, with a good calibration,
        the samples since the last solution are tested against it: a stretch that does not fit (χ² per
        sample above `max_window_chi2`: a magnet, a fault, a jump of the hard iron) is taken out of the
        sums and counted in `dropped`, the state REJECTED; after `restart_after` such stretches in a row
        the host is taken to have changed and the sums start again from the latest one. A jump is thus
        flagged first, then re-learned: the last good calibration stays applied (state REJECTED, the
        reason says so) until a solution from the new sums passes the checks, its change confirmed by
        `confirm_change_after` solutions in a row (for a 20 µT jump of the hard iron on a tumbling host:
        ~10 min flagged, then about the time a first calibration takes)."""
        self.solves += 1
        recent, self.recent = self.recent, Stats(self.n_tau)
        if (self._good is not None and not self._relearning and recent.n
                and window_chi2(recent, self._good) > self.limits.max_window_chi2):
            if self.restored == RESTORED:  # the calibration from before a restart does not fit: dropped
                self.restored, self.restored_dropped = RESTORED_DROPPED, self.restored_dropped + 1
                self._good = self._good_p = self.prior = None
                self.calibration, self.published_at_s, self.rate_T_per_s = IDENTITY, None, np.zeros(3)
                self.published += 1
                self.rejections += 1
                self.reason = f"{WINDOW_RESIDUAL} for the calibration restored after a restart: dropped"
                self.state = REJECTED
                return False
            self.misfits += 1
            self.dropped += recent.n
            self.stats.remove(recent)
            if self.misfits >= self.limits.restart_after:
                self.stats, self.misfits = recent, 0
                self.restarts += 1
                self._relearning = True
                self.prior = None
            self.rejections += 1
            self.reason = f"{WINDOW_RESIDUAL} for the last good calibration: {recent.n} samples left out"
            self.state = REJECTED
            return False
        self.misfits = 0
        last_sigma = None if self._good is None else self.calibration.sigma * _UT_SCALE
        tau = self._tau(t_s)
        cal, why, sol = _solve(self.stats, self._good_p, self.limits, last_sigma, self._insisted, recent,
                               None if self.n_tau == 1 else tau, self.drift_uT, self._good,
                               None if self.prior is None else replace(self.prior, L=self.prior.L * self._prior_weight))
        self.chi2_dof = sol.chi2_dof if sol is not None else math.nan
        self._insisted = self._insisted + 1 if why == CHANGE_TOO_LARGE else 0
        if cal is None:
            self.rejections += 1
            self.reason = why if not self._relearning else f"the host changed, re-learning: {why}"
            self.state = REJECTED
            return False
        self._relearning = False
        self.restored = NOT_RESTORED
        self.reason = None
        self.calibration = cal
        self.published += 1
        self.published_at_s = t_s
        self.rate_T_per_s = rate(sol.theta, t_s, self.drift_period_s) / UT_PER_T
        self._good = sol.theta
        self._good_p = current(sol.theta, tau)[0]
        sig = cal.sigma
        ok = (np.max(sig[:3]) * UT_PER_T <= self.limits.goal_sigma_uT
              and np.max(sig[3:]) <= self.limits.goal_sigma_soft)
        self.state = CONVERGED if ok else UNCERTAIN
        if self.first_good_at_s is None:
            self.first_good_at_s = t_s
        if ok and self.converged_at_s is None:
            self.converged_at_s = t_s
        return True

    def hard_iron_T(self, t_s: float | np.ndarray) -> np.ndarray:
        """b(t) [T] of the last good solution's model, (3,) or (n, 3) (its drift's terms included; the
        constant b before any solution)."""
        if self._good is None:
            return np.broadcast_to(self.calibration.b_T, np.shape(t_s) + (3,)).copy()
        tau = trig(t_s, self.drift_period_s)
        b = np.asarray(tau[..., :1]) * self._good[:3]
        for q in range(self.n_tau - 1):
            b = b + tau[..., q + 1:q + 2] * self._good[N_THETA + 3 * q:N_THETA + 3 * q + 3]
        return b / UT_PER_T

    def calibration_at(self, t_s: float | None) -> Calibration:
        """The last good calibration with its hard iron moved along its drift to `t_s` (at most two
        solution periods from its time; None: as published)."""
        if t_s is None or self.published_at_s is None or not np.any(self.rate_T_per_s):
            return self.calibration
        dt = float(np.clip(t_s - self.published_at_s, -2 * self.solve_every_s, 2 * self.solve_every_s))
        c = self.calibration
        return Calibration(c.b_T + self.rate_T_per_s * dt, c.D, c.cov)

    def apply(self, b_meas_T: np.ndarray, t_s: float | None = None) -> np.ndarray:
        """The sample with the last good calibration applied (unchanged before any); with `t_s`, its
        hard iron followed along the drift to that time."""
        return apply(self.calibration_at(t_s), b_meas_T)

    # --- across a restart (`fsw.persist`) -------------------------------------------------------------
    def snapshot(self) -> dict | None:
        """The last good calibration as JSON-able numbers (µT units; None before any): θ, what it
        published (b(t), D, covariance), its time and drift period, its state."""
        if self._good is None:
            return None
        c = self.calibration
        return {"theta_uT": [float(x) for x in self._good], "b_T": [float(x) for x in c.b_T],
                "D": [[float(x) for x in row] for row in c.D],
                "cov": None if c.cov is None else [[float(x) for x in row] for row in c.cov],
                "published_at_s": self.published_at_s, "drift_period_s": self.drift_period_s,
                "state": int(self.state)}

    def restore(self, snap: dict, shift_s: float | None, t_s: float = 0.0, *, restart: bool = True) -> str:
        """Take a :meth:`snapshot` from before a restart as the last good calibration, applied from the
        next sample (`t_s`: the loop's time now) and judged like a new one: the first stretch of new
        samples it does not fit drops it (`restored` 2, counted in `restored_dropped`), a solution from
        the new samples that passes the checks replaces it — with a covariance in the snapshot, that
        solution is the new samples' fit fused with the snapshot as a prior (`prior`: what was known is not
        forgotten for a noisier fresh fit; dropped when the snapshot is, or when the host is found to have
        changed). The loop's time restarted at 0: `shift_s` is
        the old time base's value at the new one's 0 (from the UTC on board before and after), with which
        the drift's terms keep their phase; None: the drift's terms are dropped (a constant hard iron, b
        as published, its σ grown by the drift's amplitude per axis: the hard iron may be anywhere on its
        cycle). `restart` False: a calibration the box made itself earlier in the same mission (handed from
        one phase to the next), applied and judged as its own, not flagged nor dropped at the first misfit.
        Returns how it was taken; ValueError when the snapshot is not one this calibration can take."""
        theta = np.asarray(snap["theta_uT"], float)
        b = np.asarray(snap["b_T"], float)
        D = np.asarray(snap["D"], float)
        cov = None if snap.get("cov") is None else np.asarray(snap["cov"], float)
        period = snap.get("drift_period_s")
        if (b.shape != (3,) or D.shape != (3, 3) or (cov is not None and cov.shape != (N_THETA, N_THETA))
                or theta.shape not in ((N_THETA,), (N_THETA + 6,))
                or not all(np.all(np.isfinite(a)) for a in (theta, b, D, *(() if cov is None else (cov,))))
                or not np.allclose(D, D.T, atol=1e-9) or not np.allclose(_sym(theta[3:N_THETA]), D, atol=1e-9)):
            raise ValueError("calibration fields of the wrong shape, not finite or not consistent")
        th = np.zeros(n_theta(self.n_tau))
        th[3:N_THETA] = theta[3:N_THETA]
        phased = (len(theta) > N_THETA and self.n_tau == 3 and shift_s is not None and math.isfinite(shift_s)
                  and period is not None and math.isclose(float(period), self.drift_period_s, rel_tol=1e-9))
        if phased:
            a = 2.0 * math.pi * shift_s / self.drift_period_s  # b(t_old) = b(t_new + shift): rotate (β_c, β_s)
            bc, bs = theta[9:12], theta[12:15]
            ca, sa = math.cos(a), math.sin(a)
            th[:3] = theta[:3]
            th[9:12] = ca * bc + sa * bs
            th[12:15] = -sa * bc + ca * bs
            how = "its drift phased by the UTC"
        else:
            th[:3] = b * UT_PER_T
            how = "its drift's terms dropped (no UTC before and after)" if len(theta) > N_THETA else "a constant host"
            if len(theta) > N_THETA and cov is not None:
                # b(t) is anywhere on its cycle now: σ of b grows by the drift's amplitude per axis
                amp_T = np.hypot(theta[9:12], theta[12:15]) / UT_PER_T
                cov = cov.copy()
                cov[:3, :3] += np.diag(amp_T ** 2)
        self.reset()
        self._good = th
        self.published_at_s = t_s
        b_now = current(th, self._tau(t_s))[0][:3] if phased else b * UT_PER_T
        self._good_p = np.concatenate([b_now, th[3:N_THETA]])
        self.calibration = Calibration(b_now / UT_PER_T, D, cov)
        if cov is not None:
            # what it knew stays known: a prior on p now, fused with the new samples' fit
            cov_uT = cov * _UT_SCALE[:, None] * _UT_SCALE[None, :]
            try:
                np.linalg.cholesky(cov_uT)  # positive definite, or no prior
                L = np.linalg.inv(cov_uT)
            except np.linalg.LinAlgError:
                L = None
            if L is not None:
                # on b(t) now; a constant host's snapshot knew b as the constant term
                tau = self._tau(t_s) if len(theta) > N_THETA else np.eye(1, self.n_tau)[0]
                A = current(th, tau)[1]
                self.prior = Prior(A, A @ th, 0.5 * (L + L.T))
        self.rate_T_per_s = rate(th, t_s, self.drift_period_s) / UT_PER_T
        self.published += 1
        self.state = int(snap["state"]) if snap.get("state") in (CONVERGED, UNCERTAIN) else UNCERTAIN
        self.restored = RESTORED if restart else NOT_RESTORED
        return how
