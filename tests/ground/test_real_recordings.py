"""The estimators on real magnetometer recordings (../shared/data, gyro as reference): on slices of each
file, at the native rate and decimated to 10 Hz, the best method's error perpendicular to B is below the
Boer formula's at the same sampling. The full table (whole files): `python -m bench.accuracy --real DIR`."""

import numpy as np
import pytest

from bench import accuracy as acc
from support import SHARED_DATA

DATA = SHARED_DATA
FILES = sorted(DATA.glob("*.csv")) if DATA.is_dir() else []

pytestmark = pytest.mark.skipif(not FILES, reason=f"no real recordings in {DATA}")


@pytest.mark.slow
@pytest.mark.parametrize("name,start_s,span_s", [
    ("xio_fusion_sensor_data.csv", 0.0, 40.0),                       # still, then hand-moved bursts
    ("broad_02_undisturbed_slow_rotation_B.csv", 60.0, 12.0),              # slow hand rotation
])
def test_best_method_beats_boer_perpendicular(name, start_s, span_s, tmp_path):
    from ground.recording import Recording, read_recording, write_recording
    rec = read_recording(DATA / name)
    m = (rec.t_s >= rec.t_s[0] + start_s) & (rec.t_s < rec.t_s[0] + start_s + span_s)
    part = tmp_path / name
    write_recording(part, Recording(rec.t_s[m], rec.b_T[m], rec.m_Nm[m], rec.w_ref_radps[m]))
    rows = acc.real_recordings([part], rates_hz=(None, 10.0), log=lambda s: None)
    for row in rows:
        boer = row["methods"]["boer"]["perp_rms_dps"]
        best = row["methods"][row["best"]]["perp_rms_dps"]
        assert np.isfinite(boer) and best < boer, (row["rate_hz"], row["methods"])
    assert "| " in acc.real_markdown(rows)
