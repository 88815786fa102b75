"""Output-error identification: Euler's equations and the attitude kinematics fitted to magnetometer samples.

The tensor J, the initial attitude and rate and the sensor offset are those that make the predicted
field in body axes closest to the measured samples (least squares weighted by the sensor noise).

- :mod:`.model` — the equations (the gravity gradient and the drag with them when the orbit is known),
  the known applied action, the parametrisation of the tensor;
- :mod:`.propagation` — RK4 of a batch of trajectories through their segments;
- :mod:`.solver` — Levenberg–Marquardt vectorised over runs, dense and block-arrow normal matrices;
- :mod:`.shooting` — the single- and multiple-shooting least-squares problems;
- :mod:`.initial` — starting values from the samples alone;
- :mod:`.identification` — the pipeline (:func:`identify`, resumable as :func:`identify_steps`);
- :mod:`.field_error` — the field model's and the calibration's errors fitted and marginalised, the
  robust covariance;
- :mod:`.profile` — the profile of the cost along the tensor's scale and its interval;
- :mod:`.cramer_rao` — the bound the fit's covariance is checked against.
"""
from .cramer_rao import cramer_rao
from .identification import FitOptions, FitResult, identify, identify_steps, prefix_fits, trajectory
from .model import FieldFn, InertiaParam, KnownAction, PositionFn
from .shooting import SingleShooting
from .solver import LMRuns, lm

__all__ = ["FieldFn", "FitOptions", "FitResult", "InertiaParam", "KnownAction", "LMRuns", "PositionFn",
           "SingleShooting", "cramer_rao", "identify", "identify_steps", "lm", "prefix_fits", "trajectory"]
