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
constant `memory_s` to follow a slow drift) and solves from time to time; nothing grows with the number
of samples. The Fisher information of θ is F = Gᵀ N G (G = ∂φ/∂θ); its inverse is the covariance.

Checks before a solution is published as good (:func:`check`): the Gauss–Newton iteration converged
and I + D is positive definite; the normalised Fisher matrix is well conditioned (a body that sees one
direction only gives a singular one); the residual's χ² per degree of freedom is plausible; the change
from the last good calibration is within bounds; each σ below its goal (then `converged`). Anything
else keeps the last good calibration and says why (`state`).

Units: interfaces in tesla and seconds; inside, µT (well-scaled numbers).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

UT_PER_T = 1e6
#: D's unique terms, in this order (also the order of the telemetry and the covariance)
D_TERMS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
N_THETA = 9
N_PHI = 10

# states of a calibration (DEBRIS_MAGCAL_STATE in the dialect has the same values)
NO_FIELD = 0        #: no field model along the orbit on board: inactive, samples pass uncorrected
COLLECTING = 1      #: too few samples yet
CONVERGED = 2       #: the published calibration is good and each σ is below its goal
UNCERTAIN = 3       #: good but not yet within the σ goals (applied: better than none)
REJECTED = 4        #: the latest solution failed a check: the last good one stays (if any)
STATE_NAMES = {NO_FIELD: "no field on board", COLLECTING: "collecting", CONVERGED: "converged",
               UNCERTAIN: "uncertain", REJECTED: "rejected"}


#: what a constant calibration against the onboard model cannot explain, taken as noise on |B| beside the
#: sensor's: the model's error (IGRF-14 degree 8: 0.07 µT RMS), the hard iron's thermal drift (~1 µT over an
#: orbit). Without it a quiet chip (0.05 µT) refuses every later minute as a misfit of a good calibration.
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


# --- the sufficient statistics ------------------------------------------------------------------------
#
# Per sample, the residual is e = z − aᵀφ = ãᵀ(φ, 1) with ã = (−a, z) = P m(B) − |B_model|² e₁₀, m(B) the
# ten monomials of B of degree ≤ 2. So Σ w e² needs only Σ w m mᵀ (monomials of degree ≤ 4: 35 sums),
# Σ w |B_model|² m and Σ w |B_model|⁴. With noise in B these are biased (the regressors are noisy:
# an errors-in-variables problem, which shrinks the scale by ~σ²/|B|², several σ of D after an orbit).
# The adjusted least squares (Kukush, Markovsky & Van Huffel 2004, consistent ellipsoid fitting) replaces
# each monomial by its Hermite polynomial in the noise — E[Heₚ(x + ε)] = xᵖ for Gaussian ε — so the
# sums estimate the noise-free ones; the raw sums are kept for the residual test.

_M2 = ((0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), (2, 0, 0), (0, 2, 0), (0, 0, 2), (1, 1, 0), (1, 0, 1), (0, 1, 1))
_M4 = tuple(sorted({tuple(p + q for p, q in zip(a, b)) for a in _M2 for b in _M2}, key=lambda e: (sum(e), e)))
_M4_INDEX = {e: k for k, e in enumerate(_M4)}
_PROD = np.array([[_M4_INDEX[tuple(p + q for p, q in zip(a, b))] for b in _M2] for a in _M2])
_M2_IN_M4 = np.array([_M4_INDEX[e] for e in _M2])
_EXP = np.array(_M4)
# ã = P m(B) − |B_model|² e₁₀
_P = np.zeros((N_PHI + 1, len(_M2)))
for _row, _col, _v in ((0, 1, -2.0), (1, 2, -2.0), (2, 3, -2.0), (3, 4, 1.0), (4, 5, 1.0), (5, 6, 1.0), (6, 7, 2.0),
                       (7, 8, 2.0), (8, 9, 2.0), (9, 0, 1.0), (10, 4, 1.0), (10, 5, 1.0), (10, 6, 1.0)):
    _P[_row, _col] = _v


def _hermite(x: np.ndarray, s2: float) -> np.ndarray:
    """(n, 5): He₀..He₄ of x with noise variance s2 (x, x² − s², x³ − 3s²x, x⁴ − 6s²x² + 3s⁴)."""
    x2 = x * x
    return np.stack((np.ones_like(x), x, x2 - s2, x2 * x - 3 * s2 * x, x2 * x2 - 6 * s2 * x2 + 3 * s2 * s2), axis=-1)


def monomials(b_uT: np.ndarray, sigma_uT: float = 0.0) -> np.ndarray:
    """(n, 35): the monomials of degree ≤ 4 of B (n, 3) in `_M4` order, noise-adjusted for σ per axis."""
    B = np.atleast_2d(np.asarray(b_uT, float))
    H = [_hermite(B[:, i], sigma_uT ** 2) for i in range(3)]
    return H[0][:, _EXP[:, 0]] * H[1][:, _EXP[:, 1]] * H[2][:, _EXP[:, 2]]


def weights(b_model_uT: np.ndarray, sigma_uT: float, sigma_model_uT: float = 0.0) -> np.ndarray:
    """w = 1/σ_z², σ_z² = 4 |B_model|² (σ² + σ_model²)."""
    h = np.atleast_1d(np.asarray(b_model_uT, float))
    return 1.0 / (4.0 * h * h * (sigma_uT ** 2 + sigma_model_uT ** 2))


@dataclass
class Stats:
    """Weighted sums of the samples' monomials, adjusted for the noise (`m`, `hm`, `h4`) and raw (`raw_*`),
    `n` samples, `weight` the effective number after forgetting."""

    m: np.ndarray = field(default_factory=lambda: np.zeros(len(_M4)))
    hm: np.ndarray = field(default_factory=lambda: np.zeros(len(_M2)))
    h4: float = 0.0
    raw_m: np.ndarray = field(default_factory=lambda: np.zeros(len(_M4)))
    raw_hm: np.ndarray = field(default_factory=lambda: np.zeros(len(_M2)))
    n: int = 0
    weight: float = 0.0

    def add(self, other: "Stats", forget: float = 1.0) -> None:
        """Add `other`'s samples, after multiplying what is here by `forget`."""
        for name in ("m", "hm", "raw_m", "raw_hm"):
            a = getattr(self, name)
            if forget != 1.0:
                a *= forget
            a += getattr(other, name)
        self.h4 = self.h4 * forget + other.h4
        self.weight = self.weight * forget + other.weight
        self.n += other.n

    def remove(self, other: "Stats") -> None:
        """Take `other`'s samples out of these sums (they were added to both, with the same forgetting)."""
        for name in ("m", "hm", "raw_m", "raw_hm"):
            getattr(self, name).__isub__(getattr(other, name))
        self.h4 -= other.h4
        self.n -= other.n
        self.weight -= other.weight

    def matrix(self, raw: bool = False) -> np.ndarray:
        """Σ w ã ãᵀ (11×11)."""
        m, hm = (self.raw_m, self.raw_hm) if raw else (self.m, self.hm)
        S = _P @ m[_PROD] @ _P.T
        cross = _P @ hm
        S[:, N_PHI] -= cross
        S[N_PHI, :] -= cross
        S[N_PHI, N_PHI] += self.h4
        return S


def contribution(b_meas_uT: np.ndarray, b_model_uT: np.ndarray, sigma_uT: float,
                 sigma_model_uT: float = 0.0) -> Stats:
    """The statistics of samples (n, 3) with the model's magnitudes (n,)."""
    h = np.atleast_1d(np.asarray(b_model_uT, float))
    w = weights(h, sigma_uT, sigma_model_uT)
    if len(h) == 1:  # one sample: the monomials on floats (numpy's per-call overhead dominates here)
        x, y, z = (float(v) for v in np.ravel(b_meas_uT))
        adj = np.array(_monomials_1(x, y, z, sigma_uT ** 2))
        raw = np.array(_monomials_1(x, y, z, 0.0))
        w0, h2 = float(w[0]), float(h[0]) ** 2
        return Stats(w0 * adj, w0 * h2 * adj[_M2_IN_M4], w0 * h2 * h2, w0 * raw, w0 * h2 * raw[_M2_IN_M4], 1, 1.0)
    adj, raw = monomials(b_meas_uT, sigma_uT), monomials(b_meas_uT)
    wh = w * h * h
    return Stats(w @ adj, wh @ adj[:, _M2_IN_M4], float(np.sum(wh * h * h)), w @ raw, wh @ raw[:, _M2_IN_M4],
                 len(h), float(len(h)))


_EXP_ROWS = tuple(tuple(int(v) for v in e) for e in _M4)


def _monomials_1(x: float, y: float, z: float, s2: float) -> list:
    def he(v):
        v2 = v * v
        return (1.0, v, v2 - s2, v2 * v - 3 * s2 * v, v2 * v2 - 6 * s2 * v2 + 3 * s2 * s2)
    hx, hy, hz = he(x), he(y), he(z)
    return [hx[p] * hy[q] * hz[r] for p, q, r in _EXP_ROWS]


def accumulate(st: Stats, b_meas_uT: np.ndarray, b_model_uT: np.ndarray, sigma_uT: float,
               sigma_model_uT: float = 0.0, forget: float = 1.0) -> Stats:
    """The statistics with samples (n, 3) and the model's magnitudes (n,) added (in place); `forget`
    multiplies what was there first."""
    st.add(contribution(b_meas_uT, b_model_uT, sigma_uT, sigma_model_uT), forget)
    return st


def normal_equations(st: Stats, raw: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """(N = Σ w a aᵀ, y = Σ w a z, Σ w z²)."""
    S = st.matrix(raw)
    return S[:N_PHI, :N_PHI], -S[:N_PHI, N_PHI], float(S[N_PHI, N_PHI])


# --- the two steps --------------------------------------------------------------------------------------

def _sym(d6: np.ndarray) -> np.ndarray:
    D = np.empty((3, 3))
    for k, (i, j) in enumerate(D_TERMS):
        D[i, j] = D[j, i] = d6[k]
    return D


def _unique(M: np.ndarray) -> np.ndarray:
    return np.array([M[i, j] for i, j in D_TERMS])


def phi_of_theta(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """φ(θ) (10) and G = ∂φ/∂θ (10×9); θ = (b [µT], D's unique terms); μ = bᵀ(I + E)b (the noise's
    mean square is taken out of the adjusted statistics)."""
    b, ID = theta[:3], np.eye(3) + _sym(theta[3:])
    M = ID @ ID
    phi = np.concatenate((M @ b, _unique(M - np.eye(3)), [b @ M @ b]))
    G = np.zeros((N_PHI, N_THETA))
    G[:3, :3] = M
    G[9, :3] = 2 * M @ b
    for k, (i, j) in enumerate(D_TERMS):
        Ek = np.zeros((3, 3))
        Ek[i, j] = Ek[j, i] = 1.0
        dM = Ek @ ID + ID @ Ek
        G[:3, 3 + k] = dM @ b
        G[3:9, 3 + k] = _unique(dM)
        G[9, 3 + k] = b @ dM @ b
    return phi, G


def cost(N: np.ndarray, y: np.ndarray, zz: float, phi: np.ndarray) -> float:
    """Σ w (z − aᵀφ)² from the normal equations."""
    return float(zz - 2 * phi @ y + phi @ N @ phi)


def centred_estimate(st: Stats) -> np.ndarray | None:
    """Step one: θ from the unconstrained linear fit (μ free), or None when it has no valid solution
    (singular, or I + E not positive definite)."""
    N, y, _ = normal_equations(st)
    try:
        phi = np.linalg.solve(N, y)
    except np.linalg.LinAlgError:
        return None
    M = np.eye(3) + _sym(phi[3:9])
    ev, V = np.linalg.eigh(M)
    if not np.all(np.isfinite(ev)) or ev.min() <= 0.0:
        return None
    ID = (V * np.sqrt(ev)) @ V.T
    b = np.linalg.solve(M, phi[:3])
    return np.concatenate((b, _unique(ID - np.eye(3))))


@dataclass(frozen=True)
class Solution:
    theta: np.ndarray        #: (b [µT], D's unique terms)
    fisher: np.ndarray       #: 9×9, in those units
    chi2_dof: float          #: the raw residual's χ² per degree of freedom
    iterations: int
    converged: bool          #: the Gauss–Newton step became negligible


def refine(st: Stats, theta0: np.ndarray, max_iter: int = 20, tol: float = 1e-6) -> Solution:
    """Step two: Gauss–Newton (Fisher scoring) on θ from `theta0` over the adjusted statistics, the step
    halved while it does not lower the cost."""
    N, y, zz = normal_equations(st)
    theta = np.array(theta0, float)
    phi, G = phi_of_theta(theta)
    c = cost(N, y, zz, phi)
    done = False
    it = 0
    while it < max_iter:
        it += 1
        F = G.T @ N @ G
        g = G.T @ (y - N @ phi)
        try:
            step = np.linalg.solve(F, g)
        except np.linalg.LinAlgError:
            break
        for _ in range(30):
            cand = theta + step
            phi_c, G_c = phi_of_theta(cand)
            c_c = cost(N, y, zz, phi_c)
            if c_c <= c or not np.isfinite(c):
                break
            step = 0.5 * step
        else:
            break
        theta, phi, G, c = cand, phi_c, G_c, c_c
        # converged when the step is small against its own σ
        if float(step @ F @ step) < tol:
            done = True
            break
    F = G.T @ N @ G
    dof = max(st.weight - N_THETA, 1.0)
    raw = cost(*normal_equations(st, raw=True), phi)
    return Solution(theta, F, max(raw, 0.0) / dof, it, done)


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
    #: change from the last good calibration refused when above both this (b per axis, µT; D's terms:
    #: a thermal drift's worth between two solutions) and `max_change_sigmas` of the σ of the
    #: difference (the last good one's and this one's) ...
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
    return cost(*normal_equations(recent, raw=True), phi_of_theta(theta)[0]) / max(recent.weight, 1e-12)


def normalised_condition(F: np.ndarray) -> float:
    d = np.diag(F)
    if not np.all(np.isfinite(F)) or np.any(d <= 0):
        return math.inf
    s = 1.0 / np.sqrt(d)
    return float(np.linalg.cond(F * s[:, None] * s[None, :]))


def check(sol: Solution, last_good: np.ndarray | None, lim: Limits, last_sigma: np.ndarray | None = None,
          insisted: int = 0, recent: Stats | None = None) -> tuple[str | None, np.ndarray | None]:
    """(None, covariance) when `sol` may be published, else (why not, None). The covariance is the
    inverse Fisher matrix scaled by the residual's χ²/dof when that is above 1 (σ_z is approximate).
    `last_sigma`: the last good calibration's σ (µT units); `insisted`: how many solutions in a row were
    refused for their change already; `recent`: the samples since the last solution."""
    th = sol.theta
    if not sol.converged or not np.all(np.isfinite(th)):
        return "did not converge", None
    cond = normalised_condition(sol.fisher)
    if cond > lim.max_condition:
        return f"ill-conditioned (Fisher condition {cond:.3g})", None
    cov = np.linalg.inv(sol.fisher) * max(1.0, sol.chi2_dof)
    if np.any(np.diag(cov) <= 0):
        return "ill-conditioned (covariance not positive)", None
    if sol.chi2_dof > lim.max_chi2_dof:
        return f"residual too large (chi2/dof {sol.chi2_dof:.3g})", None
    if recent is not None and recent.n > 0:
        chi2 = window_chi2(recent, th)
        if chi2 > lim.max_window_chi2:
            return f"{WINDOW_RESIDUAL} (chi2/sample {chi2:.3g})", None
    ev = np.linalg.eigvalsh(_sym(th[3:]))
    if np.max(np.abs(th[:3])) > lim.max_hard_iron_uT or np.max(np.abs(ev)) > lim.max_soft_iron:
        return "implausible values", None
    if last_good is not None and insisted < lim.confirm_change_after:
        bound = np.array([lim.max_change_uT] * 3 + [lim.max_change_soft] * 6)
        if last_sigma is not None:
            both = np.sqrt(last_sigma ** 2 + np.diag(cov))
            bound = np.maximum(bound, lim.max_change_sigmas * both)
        if np.any(np.abs(th - last_good) > bound):
            return CHANGE_TOO_LARGE, None
    return None, cov


_UT_SCALE = np.array([UT_PER_T] * 3 + [1.0] * 6)


def to_calibration(theta: np.ndarray, cov_uT: np.ndarray | None) -> Calibration:
    """θ (µT) and its covariance to a :class:`Calibration` (T)."""
    cov = None if cov_uT is None else cov_uT / _UT_SCALE[:, None] / _UT_SCALE[None, :]
    return Calibration(theta[:3] / UT_PER_T, _sym(theta[3:]), cov)


def estimate(b_meas_T: np.ndarray, b_model_T: np.ndarray, sigma_T: float, sigma_model_T: float = 0.0,
             limits: Limits = Limits()) -> tuple[Calibration | None, str | None, Solution | None]:
    """Batch TWOSTEP on samples (n, 3) and the model's magnitudes (n,): (calibration, None, solution)
    when it passes :func:`check`, else (None, why, solution or None)."""
    st = accumulate(Stats(), np.asarray(b_meas_T) * UT_PER_T, np.asarray(b_model_T) * UT_PER_T,
                    sigma_T * UT_PER_T, sigma_model_T * UT_PER_T)
    return _solve(st, None, limits)


def _solve(st: Stats, last_good: np.ndarray | None, lim: Limits,
           last_sigma: np.ndarray | None = None, insisted: int = 0, recent: Stats | None = None):
    if st.n < 2 * N_PHI:
        return None, "too few samples", None
    theta0 = centred_estimate(st)
    starts = [t for t in (theta0, last_good, np.zeros(N_THETA)) if t is not None]
    sol = None
    for t0 in starts:
        sol = refine(st, t0)
        if sol.converged:
            break
    why, cov = check(sol, last_good, lim, last_sigma, insisted, recent)
    if why:
        return None, why, sol
    return to_calibration(sol.theta, cov), None, sol


# --- the flight form ------------------------------------------------------------------------------------

class MagCal:
    """Recursive TWOSTEP: :meth:`update` with each sample (B_meas [T], |B_model| [T], t [s]); every
    `solve_every_s` of sample time the statistics are solved and the result checked. `calibration` is
    the last good one (identity before any), `state` says where it stands, `reason` why the latest
    solution was refused. `memory_s`: time constant of the exponential forgetting (None: none)."""

    def __init__(self, sigma_T: float, *, sigma_model_T: float = 0.0, solve_every_s: float = 60.0,
                 min_samples: int = 200, memory_s: float | None = None, limits: Limits = Limits()) -> None:
        self.sigma_uT = sigma_T * UT_PER_T
        self.sigma_model_uT = sigma_model_T * UT_PER_T
        self.solve_every_s = solve_every_s
        self.min_samples = min_samples
        self.memory_s = memory_s
        self.limits = limits
        self.reset()

    def reset(self) -> None:
        self.stats = Stats()
        self.recent = Stats()  # the samples since the last solution
        self.calibration = IDENTITY
        self._good: np.ndarray | None = None
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
        self._t_last: float | None = None
        self._t_solve: float | None = None
        self._insisted = 0

    @property
    def samples(self) -> int:
        return self.stats.n

    @property
    def good(self) -> bool:
        """A calibration that passed the checks is being applied."""
        return self._good is not None

    def update(self, b_meas_T: np.ndarray, b_model_mag_T: float, t_s: float) -> bool:
        """Add a sample; True when a new calibration was published."""
        if not (np.all(np.isfinite(b_meas_T)) and math.isfinite(b_model_mag_T) and b_model_mag_T > 0):
            return False
        forget = 1.0
        if self.memory_s is not None and self._t_last is not None:
            forget = math.exp(-max(t_s - self._t_last, 0.0) / self.memory_s)
        self._t_last = t_s
        c = contribution(np.asarray(b_meas_T) * UT_PER_T, b_model_mag_T * UT_PER_T, self.sigma_uT,
                         self.sigma_model_uT)
        self.stats.add(c, forget)
        self.recent.add(c, forget)
        if self._t_solve is None:
            self._t_solve = t_s
        if self.stats.n < self.min_samples or t_s - self._t_solve < self.solve_every_s:
            return False
        self._t_solve = t_s
        return self.solve(t_s)

    def solve(self, t_s: float) -> bool:
        """Solve the statistics now; True when the result was published. First, with a good calibration,
        the samples since the last solution are tested against it: a stretch that does not fit (χ² per
        sample above `max_window_chi2`: a magnet, a fault) is taken out of the sums and counted in
        `dropped`; after `restart_after` such stretches in a row the host is taken to have changed and the
        sums start again from the latest one (the last good calibration stays applied meanwhile)."""
        self.solves += 1
        recent, self.recent = self.recent, Stats()
        if self._good is not None and recent.n and window_chi2(recent, self._good) > self.limits.max_window_chi2:
            self.misfits += 1
            self.dropped += recent.n
            self.stats.remove(recent)
            if self.misfits >= self.limits.restart_after:
                self.stats, self.misfits = recent, 0
                self.restarts += 1
            self.rejections += 1
            self.reason = f"{WINDOW_RESIDUAL} for the last good calibration: {recent.n} samples left out"
            self.state = REJECTED
            return False
        self.misfits = 0
        last_sigma = None if self._good is None else self.calibration.sigma * _UT_SCALE
        cal, why, sol = _solve(self.stats, self._good, self.limits, last_sigma, self._insisted, recent)
        self.chi2_dof = sol.chi2_dof if sol is not None else math.nan
        self._insisted = self._insisted + 1 if why == CHANGE_TOO_LARGE else 0
        if cal is None:
            self.rejections += 1
            self.reason = why
            self.state = REJECTED
            return False
        self.reason = None
        self.calibration = cal
        self.published += 1
        self._good = sol.theta
        sig = cal.sigma
        ok = (np.max(sig[:3]) * UT_PER_T <= self.limits.goal_sigma_uT
              and np.max(sig[3:]) <= self.limits.goal_sigma_soft)
        self.state = CONVERGED if ok else UNCERTAIN
        if self.first_good_at_s is None:
            self.first_good_at_s = t_s
        if ok and self.converged_at_s is None:
            self.converged_at_s = t_s
        return True

    def apply(self, b_meas_T: np.ndarray) -> np.ndarray:
        """The sample with the last good calibration applied (unchanged before any)."""
        return apply(self.calibration, b_meas_T)
