"""The two least-squares problems of the fit: single and multiple shooting.

A single trajectory over a long record ("single shooting") has a small basin of attraction: a rate
that is slightly wrong early makes the prediction wrap around later. Multiple shooting (Bock 1984)
cuts the record into segments of a few tens of samples, each with its own initial (q, ω), tied
together by continuity defects whose weights the caller tightens from loose to tight
(:mod:`~.identification`).
"""
from __future__ import annotations

import copy

from dataclasses import dataclass

import numpy as np

from ..rotations import quat_conj, quat_exp, quat_mul
from .initial import retilt
from .model import FieldFn, InertiaParam, KnownAction
from .propagation import Pass, Segments
from .solver import BlockArrow, Dense, complete, evaluate_steps

# --- single shooting ----------------------------------------------------------------------------------

@dataclass
class ErrorTerms:
    """The error terms a single-shooting fit estimated (its columns, `identification.error_columns`): one
    offset (3,) per dipole state of the known action (``kit_T`` (G, 3)), then the host's hard-iron drift,
    Legendre degree 1…D over the record per body axis (``drift_T`` (D, 3)); with their 1-σ."""

    kit_T: np.ndarray
    kit_sigma_T: np.ndarray
    drift_T: np.ndarray
    drift_sigma_T: np.ndarray


class SingleShooting:
    """One trajectory per run over the first ``n`` samples:
    θ = [θ_I | ω₀/ω_s (3) | δθ₀ (3) | b/σ_B (3) | e (m)].

    ``q_ref`` (R, 4) the attitude the rotation vector δθ₀ perturbs (body side); ``b_meas`` (R, n_all, 3).
    ``error_columns`` (m, n_all, 3): errors of the samples linear in parameters e of their own, added to
    the prediction as σ_B Σ_j e_j C_j (`error_terms`: the kit field's compensation error while the
    magnets act, the host's hard-iron drift); their Jacobian is C itself, so they cost no trajectories
    and are added to the nominal trajectory's prediction only (:meth:`predicted_T`).
    """

    def __init__(self, t_s: np.ndarray, b_meas: np.ndarray, b_samples: np.ndarray, action: KnownAction,
                 b_inertial: FieldFn, inertia: InertiaParam, q_ref: np.ndarray, sigma_b_T: float, *,
                 n: int | None = None, fit_bias: bool = True, omega_scale: float = 0.01,
                 h_max_s: float = 1.0, fd_step: float = 1e-6, error_columns: np.ndarray | None = None) -> None:
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
        cols = np.zeros((0, len(self.t), 3)) if error_columns is None else np.asarray(error_columns, float)
        self.columns = cols[:, :self.n]

    def replicated(self, run: int, k: int) -> "SingleShooting":
        """The same problem with `k` runs, each run `run`'s samples and reference attitude (one record
        fitted from `k` starts; modes whose tensor has no per-run shape)."""
        out = copy.copy(self)
        out.b_meas = np.repeat(self.b_meas[run][None], k, axis=0)
        out.q_ref = np.repeat(self.q_ref[run][None], k, axis=0)
        return out

    @property
    def error_index(self) -> int:
        """Index in θ of the first error term."""
        return self.inertia.n + 6 + (3 if self.fit_bias else 0)

    @property
    def n_params(self) -> int:
        return self.error_index + len(self.columns)

    def unpack(self, theta: np.ndarray, runs: np.ndarray):
        n = self.inertia.n
        p = self.inertia.to_p(theta[:, :n], runs)
        w0 = theta[:, n:n + 3] * self.omega_scale
        q0 = quat_mul(self.q_ref[runs], quat_exp(theta[:, n + 3:n + 6]))
        bias = theta[:, n + 6:n + 9] * self.sigma if self.fit_bias else np.zeros((len(theta), 3))
        return p, q0, w0, bias

    def errors_T(self, theta: np.ndarray) -> np.ndarray | None:
        """The error terms' part of the prediction (nb, n, 3) [T] at θ (nb, P); None without terms."""
        if not len(self.columns):
            return None
        return self.sigma * np.einsum("bm,mna->bna", theta[:, self.error_index:], self.columns)

    def error_terms(self, theta: np.ndarray, cov: np.ndarray, n_kit: int) -> ErrorTerms | None:
        """The error terms at θ (P,) with covariance `cov` (P, P), the first `n_kit` × 3 the dipole states'
        offsets (None without terms)."""
        m = len(self.columns)
        if not m:
            return None
        i, G = self.error_index, int(n_kit)
        v = theta[i:i + m] * self.sigma
        s = np.sqrt(np.clip(np.diag(cov)[i:i + m], 0.0, None)) * self.sigma
        return ErrorTerms(v[:3 * G].reshape(G, 3), s[:3 * G].reshape(G, 3), v[3 * G:].reshape(-1, 3),
                          s[3 * G:].reshape(-1, 3))

    def predicted_T(self, pred: np.ndarray, thetas: np.ndarray) -> np.ndarray:
        """The predicted samples (nb, n, 3) [T]: the trajectories' `pred` (nb, ≥n, 3) at θ (nb, P) with
        their error terms."""
        e = self.errors_T(thetas)
        return pred[:, :self.n] if e is None else pred[:, :self.n] + e

    def start(self, thetas: np.ndarray, runs: np.ndarray, keep_states: bool = False) -> Pass:
        """The trajectories of θ (their `pred` without the error terms: :meth:`predicted_T`)."""
        p, q0, w0, bias = self.unpack(thetas, runs)
        return Pass(self.seg, np.zeros(len(thetas), int), p.T, q0.T, w0.T, bias.T, keep_states,
                    u=self.inertia.to_moments(thetas[:, :self.inertia.n]))

    def begin(self, thetas: np.ndarray, runs: np.ndarray) -> tuple[Pass, tuple]:
        R, P = thetas.shape
        k = self.error_index                          # perturbed: the rest is linear (its columns)
        th = np.repeat(thetas[:, None, :], k + 1, axis=1)
        th[:, 1:, :k] += self.step * np.eye(k)[None]
        return self.start(th.reshape(-1, P), np.repeat(runs, k + 1)), (runs, R, k, thetas)

    def evaluate(self, thetas: np.ndarray, runs: np.ndarray):
        return complete(evaluate_steps(self, thetas, runs, None))

    def residuals_jacobian(self, thetas: np.ndarray, runs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The whitened residuals (R, n, 3) and their Jacobian (R, P, n, 3) at ``thetas``."""
        ps, ctx = self.begin(thetas, runs)
        ps.advance()
        return self._residuals_jacobian(ps, *ctx)

    def _residuals_jacobian(self, ps: Pass, runs: np.ndarray, R: int, k: int,
                            thetas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = self.n
        pred = ps.pred[:, :n].reshape(R, k + 1, n, 3)
        J = (pred[:, 1:] - pred[:, :1]) / (self.step * self.sigma)    # the error terms cancel: not in pred
        if len(self.columns):
            J = np.concatenate([J, np.broadcast_to(self.columns[None], (R,) + self.columns.shape)], axis=1)
        return (self.predicted_T(pred[:, 0], thetas) - self.b_meas[runs, :n]) / self.sigma, J

    def finish(self, ps: Pass, ctx: tuple):
        R = ctx[1]
        n = self.n
        r, Jm = self._residuals_jacobian(ps, *ctx)
        P = Jm.shape[1]
        r, Jm = r.reshape(R, -1), Jm.reshape(R, P, -1)
        bad = ~(np.all(np.isfinite(r), axis=1) & np.all(np.isfinite(Jm), axis=(1, 2)))
        r = np.where(bad[:, None], 0.0, r)
        Jm = np.where(bad[:, None, None], 0.0, Jm)
        cost = np.where(bad, np.inf, np.sum(r * r, axis=1))
        return (cost, cost, Dense(np.einsum("rkm,rlm->rkl", Jm, Jm)), np.einsum("rkm,rm->rk", Jm, r),
                max(3 * n - P, 1))

    def trajectory(self, theta: np.ndarray, run: int = 0) -> dict:
        ps = self.start(theta[None, :], np.array([run]), keep_states=True)
        ps.advance()
        st = ps.states[0, :self.n]
        return {"b_body_T": self.predicted_T(ps.pred, theta[None, :])[0], "q": st[:, :4], "omega_radps": st[:, 4:]}


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
        def dq(qe, qs):
            d = quat_mul(quat_conj(qe), qs)
            return 2.0 * d[..., 1:] * np.sign(d[..., :1] + 1e-300)

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
