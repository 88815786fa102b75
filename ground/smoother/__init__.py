"""Ground smoothers of the body rate: every sample of a recording informs every estimate.

The package: :mod:`.rts` (the random-walk RTS smoother, the result type), :mod:`.batch_fit` (the batch
output-error fit), :mod:`.auto` (the Euler RTS smoother and "auto"); their public names are here.

Two models, both on the attitude filter of the flight software (fsw/estimation/attitude_kalman.py), with the
field model along the orbit when one is given (which removes the field-motion floor) and the field
fixed in inertial space otherwise (laboratory recordings):

- :func:`rts_smooth` — fixed-interval Rauch–Tung–Striebel smoother (Rauch, Tung & Striebel 1965;
  Bar-Shalom et al. 2001 §8.6) over the multiplicative EKF with ω a random walk. Works for any
  motion; the strength of the random walk (κ, the scale of the torque-free |ω̇| ≤ κ|ω|²) is chosen by
  maximum likelihood over a small grid, the pass is repeated from the smoothed start
  (re-linearisation), and with a field model the passes from several initial angles about B are
  combined as a Gaussian sum (`ground.angle_sum`: the samples barely fix that angle).
- :func:`euler_fit` — output-error fit of the torque-free Euler equations and the kinematics to the
  whole record (batch nonlinear least squares, Gauss–Newton / Levenberg–Marquardt): parameters are
  the attitude and rate at the first sample, the inertia shape ln(J₂/J₁), ln(J₃/J₁) (torque-free
  motion depends only on the ratios) or a known tensor, and, with no field model, the inertial field.
  Residual Jacobians come from the error-state transition matrices of the same propagation; the
  record is brought in over growing windows (continuation), so that a rate known only roughly at
  first never has to be extrapolated far. 1-σ from s²(JᵀJ)⁻¹ mapped through the transition matrices,
  widened by the spread between the fit's near-equivalent minima.
  An asymmetric tumbling body has ω varying in body axes; a random walk then lags, this model does not.
- :func:`smooth` — both, and the Euler fit kept when it explains the data (χ²/dof ≤ `chi2_accept`) and
  agrees with the Euler RTS smoother within their combined σ (:func:`auto_choice`).

The rule of "auto" (:func:`auto_result`): it never returns a solution that another solution's σ
excludes. The candidates are the batch Euler fit, the Euler RTS smoother and the random-walk RTS
smoother; one excludes another when the other lies more than 3 of its σ away on some axis at more than
a quarter of the samples (:func:`excludes`); only the candidates that explain the data judge (χ²/dof
≤ 1.5; the random-walk smoother always, it assumes least; a batch fit already rejected as in a wrong
minimum does not). The first of the order Euler fit → Euler RTS →
random walk (the random walk before the Euler RTS smoother when it explains the samples better: a lower
innovation likelihood `nll`) that no judge excludes is returned; when each is excluded by another (they disagree beyond
their σ and the data do not say which is right), the first is returned with its σ widened to cover
the others (:func:`covering`). Without a field model the ground tool then widens every σ by the field's
own turning (`fsw.estimation.rate_formulas.widen_for_field_turn`).

A model the samples reject (:func:`model_error_checked`): a batch fit that fails the χ² test (0.1 %) or
explains the data worse than χ²/dof 1.5 has σ² + (ω − ω_ref)² + σ_ref², ref the likelier of the Euler RTS
and random-walk smoothers; the Euler RTS smoother has the same against the random walk when that is
likelier and its σ excludes it. A covariance says what the samples fix given the model; Euler's
equations carry the rate along B, which the samples barely see, and where the motion is not theirs (a
libration, a torque) that part of σ is void.
"""
from __future__ import annotations

from .auto import (CHI2_TEST_Z, EXCLUDE_SHARE, EXCLUDE_Z, auto_choice, auto_order, auto_result, chi2_consistent,
                   covering, disagreement, euler_rts_after_fit, euler_rts_smooth, excludes, model_error_checked,
                   smooth, widened_for_model_error)
from .batch_fit import MODE_KEEP_DCHI2, MODE_SEARCH_DCHI2, euler_fit, euler_fit_checked, euler_fit_from_filter
from .rts import SHAPE_SIGMA_FLOOR, FieldFn, Smoothed, rts, rts_smooth, tabulated, variance_scale

__all__ = ["CHI2_TEST_Z", "EXCLUDE_SHARE", "EXCLUDE_Z", "FieldFn", "MODE_KEEP_DCHI2", "MODE_SEARCH_DCHI2",
           "SHAPE_SIGMA_FLOOR", "Smoothed", "auto_choice", "auto_order", "auto_result", "chi2_consistent", "covering",
           "disagreement", "euler_fit", "euler_fit_checked", "euler_fit_from_filter", "euler_rts_after_fit",
           "euler_rts_smooth", "excludes", "model_error_checked", "rts", "rts_smooth", "smooth", "tabulated",
           "variance_scale", "widened_for_model_error"]
