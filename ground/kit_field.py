"""The de-orbit kit's field out of a recording, before the ground's estimators see it.

A recording decoded from the box holds the sensor's own field (the kit's magnets included: steps of
50-100 µT at every capsule event) and, in the optional columns ``kit_bx_uT, kit_by_uT, kit_bz_uT`` and
``flags``, what the box took out of each sample and whether it was taken while a shutter or a magnet
moved (DEBRIS_SAMPLE_FLAGS_KIT_MOVING: the kit's field then unknown). :func:`take_out` does on the
ground what the box does on board: it drops the flagged samples (and any whose kit field is unknown,
NaN) and subtracts the kit's field from the others. `ground.estimate`, `ground.inertia` and
`ground.replay` call it by default and say what it did on their first line; ``--kit-raw`` keeps the
samples as recorded. A recording without the columns (an old export, a laboratory file) passes through
unchanged.
"""
from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from fsw.telemetry.dialect import mavlink

from .recording import Recording

KIT_MOVING = mavlink.DEBRIS_SAMPLE_FLAGS_KIT_MOVING


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--kit-raw", action="store_true",
                    help="keep the recording's kit field and the samples flagged KIT_MOVING (default: the kit's "
                         "field the box recorded is subtracted and flagged samples are skipped)")


def take_out(rec: Recording, *, raw: bool = False) -> tuple[Recording, str]:
    """`rec` without the kit: flagged samples dropped, the recorded kit field subtracted; and a line
    saying what was done (with counts). `raw`: unchanged, the line says so."""
    has_kit, has_flags = rec.kit_T is not None, rec.flags is not None
    if not has_kit and not has_flags:
        return rec, "kit field: none recorded (no kit_b*_uT / flags columns), samples as recorded"
    n = len(rec)
    flagged = (rec.flags & KIT_MOVING) != 0 if has_flags else np.zeros(n, dtype=bool)
    unknown = ~np.all(np.isfinite(rec.kit_T), axis=1) if has_kit else np.zeros(n, dtype=bool)
    if raw:
        return rec, (f"kit field: kept raw (--kit-raw): {int(flagged.sum())} of {n} samples flagged KIT_MOVING "
                     "used, the recorded kit field not subtracted")
    keep = ~(flagged | unknown)
    kit = rec.kit_T[keep] if has_kit else np.zeros((int(keep.sum()), 3))
    out = dataclasses.replace(rec.rows(keep), kit_T=None, flags=None)  # the kit is out: no columns of it
    out.b_T = out.b_T - kit
    peak = float(np.max(np.linalg.norm(kit, axis=1))) * 1e6 if len(kit) else 0.0
    line = (f"kit field: {int(flagged.sum())} of {n} samples flagged KIT_MOVING skipped"
            + (f", {int((unknown & ~flagged).sum())} with an unknown kit field skipped" if unknown.any() else "")
            + f"; the recorded kit field subtracted from {int(np.any(kit != 0, axis=1).sum())} samples "
              f"(up to {peak:.1f} µT; --kit-raw keeps them)")
    return out, line
