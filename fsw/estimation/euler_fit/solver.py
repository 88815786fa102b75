"""Least squares for the fit: Levenberg–Marquardt vectorised over runs, on normal matrices kept dense
(single shooting) or in the block-arrow form of multiple shooting, with independent Gaussian priors.

A problem has ``begin(thetas, runs)`` → (a :class:`~.propagation.Pass`, context) and ``finish(pass,
context)`` → (cost, data cost, normal matrix, gradient, dof); :func:`evaluate_steps` and
:func:`lm_steps` are generators that yield between integration steps, so that a caller can spread the
work over time.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
            done = acc & ~first[act]
            done[done] = gain[done] < tol + rtol * c[done]   # accepted: finite costs only
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
