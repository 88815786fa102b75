"""The host-magnetics calibration of a recording, for the ground's refinements (`ground.estimate`,
`ground.inertia`): given in a file (``--magcal FILE.json``) or estimated from the recording itself
(``--estimate-magcal``: the same TWOSTEP as on board, `fsw.estimation.magcal`, against the field's
magnitude along the recording's orbit), and applied to every sample before the fit:
B = (I + D)(B_meas − b).

The file, JSON (what `Calibration.to_json` writes; other keys are ignored)::

    {"hard_iron_uT": [bx, by, bz],                       # b, sensor axes, µT
     "soft_iron": [[D11, D12, D13], [D12, D22, D23], [D13, D23, D33]]}   # D, symmetric, I + D positive definite

The DEBRIS_MAGCAL message carries the same numbers (hard_iron in µT; soft_iron as D11, D22, D33, D12,
D13, D23). Estimating needs an orbit (``--scenario``, ``--tle``/``--utc0`` or the recording's metadata)
and a record over which the body turns through many directions (an orbit of a tumble); a calibration
that fails its checks (`magcal.check`) is an error, not applied.

Without either option, a calibration in the recording's metadata (``magcal_hard_iron_uT``,
``magcal_soft_iron``: the box's last, written by `ground.decode`; not applied to the samples) is applied;
``--no-magcal`` leaves the samples as they are.
"""
from __future__ import annotations

import argparse
import json
import os
import stat

import numpy as np

from fsw.estimation import magcal as mc

from .recording import Recording


def add_arguments(ap: argparse.ArgumentParser) -> None:
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--magcal", metavar="FILE.json",
                   help="apply this host-magnetics calibration (hard/soft iron, JSON: see ground/magcal.py) "
                        "to the samples before fitting")
    g.add_argument("--estimate-magcal", action="store_true",
                   help="estimate the host's hard/soft iron from the recording (needs its orbit) and apply it "
                        "before fitting")
    g.add_argument("--no-magcal", action="store_true",
                   help="do not apply the calibration of the recording's metadata (the box's, applied by default)")


def from_metadata(md: dict) -> mc.Calibration | None:
    """The calibration the box applied, from a recording's ``magcal_hard_iron_uT`` and ``magcal_soft_iron``
    (None when absent); ValueError naming the key when it is not one."""
    if "magcal_hard_iron_uT" not in md:
        return None
    try:
        b = [float(v) for v in md["magcal_hard_iron_uT"].split(",")]
        D = [float(v) for v in md.get("magcal_soft_iron", "0, 0, 0, 0, 0, 0, 0, 0, 0").split(",")]
        if len(D) != 9:
            raise ValueError
        return mc.Calibration.from_json({"hard_iron_uT": b, "soft_iron": np.reshape(D, (3, 3)).tolist()})
    except ValueError as e:
        why = f": {e}" if str(e) else ""
        raise ValueError(f"the recording's magcal_hard_iron_uT / magcal_soft_iron are not a calibration "
                         f"(3 and 9 numbers){why}") from None


def load(path: str) -> mc.Calibration:
    """The calibration in a JSON file; ValueError (naming the file) when it is not one (a FIFO or a device
    is refused before it is opened: reading one could wait for ever)."""
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            raise ValueError(f"--magcal {path}: not a regular file")
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
    except UnicodeDecodeError:
        raise ValueError(f"--magcal {path}: not a JSON text file") from None
    except json.JSONDecodeError as e:
        raise ValueError(f"--magcal {path}: not JSON ({e.msg}, line {e.lineno})") from None
    try:
        return mc.Calibration.from_json(data)
    except ValueError as e:
        raise ValueError(f"--magcal {path}: {e}") from None


def calibrate(rec: Recording, args, field, sigma_b_T: float) -> tuple[Recording, str | None]:
    """The recording with the calibration of `args` applied (unchanged without one) and a line saying
    what was applied. `field`: B_ECI(t) along the recording's orbit (callable) or None."""
    rec, how, _ = calibrate_with_sigma(rec, args, field, sigma_b_T)
    return rec, how


def calibrate_with_sigma(rec: Recording, args, field, sigma_b_T: float
                         ) -> tuple[Recording, str | None, np.ndarray | None]:
    """:func:`calibrate`, and the applied calibration's hard-iron 1-σ per axis (T; None when none was applied
    or its covariance is not known: a file without one)."""
    if getattr(args, "magcal", None):
        cal = load(args.magcal)
        how = f"host-magnetics calibration from {args.magcal}"
    elif getattr(args, "estimate_magcal", False):
        if field is None:
            raise ValueError("--estimate-magcal needs the recording's orbit (--scenario, --tle/--utc0 or the "
                             "recording's orbit metadata)")
        mag = np.linalg.norm(np.asarray(field(rec.t_s), float), axis=1)
        cal, why, _ = mc.estimate(rec.b_T, mag, sigma_b_T, mc.MODEL_SIGMA_T)
        if cal is None:
            raise ValueError(f"--estimate-magcal: no calibration from this recording: {why}")
        how = "host-magnetics calibration estimated from the recording"
    else:
        cal = None if getattr(args, "no_magcal", False) else from_metadata(rec.metadata)
        if cal is None:
            return rec, None, None
        md = rec.metadata
        how = (f"host-magnetics calibration from the recording's metadata (the box's, {md.get('magcal_state', '?')} "
               f"at t = {md.get('magcal_t_s', '?')} s; --no-magcal leaves it out)")
    s = cal.sigma
    how += (": hard iron " + ", ".join(f"{v * 1e6:.2f}" for v in cal.b_T) + " µT"
            + ("" if cal.cov is None else " (±" + ", ".join(f"{v * 1e6:.2f}" for v in s[:3]) + ")")
            + ", soft iron diagonal " + ", ".join(f"{cal.D[i, i]:+.4f}" for i in range(3)))
    hard_sigma_T = None if cal.cov is None else np.asarray(s[:3], float)
    if hard_sigma_T is None and not (getattr(args, "magcal", None) or getattr(args, "estimate_magcal", False)):
        hard_sigma_T = _metadata_hard_iron_sigma_T(rec.metadata)
    return (Recording(rec.t_s, mc.apply(cal, rec.b_T), rec.m_Nm, rec.w_ref_radps, rec.metadata, rec.path), how,
            hard_sigma_T)


def _metadata_hard_iron_sigma_T(md: dict) -> np.ndarray | None:
    """The box's published hard-iron 1-σ (``magcal_hard_iron_sigma_uT``) in T; None when absent or not three
    finite positive numbers (NaN before any calibration)."""
    try:
        s = np.array([float(v) for v in md.get("magcal_hard_iron_sigma_uT", "").split(",")]) * 1e-6
    except ValueError:
        return None
    return s if s.shape == (3,) and np.all(np.isfinite(s)) and np.all(s > 0) else None
