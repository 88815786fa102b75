"""`python -m ground.deorbit_attitude`: the de-orbit controller's inputs from a tlog against SITL's truth
(DEBRIS_DEORBIT_ATTITUDE.truth_ypr), the RMS printed, the CSV and the plot written; usage and runtime errors."""
import csv
import math

import pytest

from fsw.deorbit.onboard_attitude import AttitudeReport
from fsw.telemetry.dialect import mavlink
from fsw.telemetry.telemetry import Telemetry
from ground import deorbit_attitude
from ground.decode import Decoder, tlog_record
from support import Capture

pytestmark = pytest.mark.ground
TRUSTED, UNTRUSTED = mavlink.DEBRIS_CONTROLLER_ATTITUDE_TRUSTED, mavlink.DEBRIS_CONTROLLER_ATTITUDE_UNTRUSTED


def _tlog(path, rows):
    """rows: (t_s, estimate (yaw, pitch, roll), truth (yaw, pitch, roll), source)."""
    cap = Capture()
    tlm = Telemetry(cap)
    for t, est, tru, src in rows:
        tlm.deorbit_attitude(t, AttitudeReport(*est, (0.0, 0.0, 0.0), (0.03, 0.04), 1e-5, src, 1), held=0,
                             truth_ypr=tru)
    path.write_bytes(b"".join(tlog_record(m, 1_750_000_000.0 + k) for k, m in enumerate(cap.messages())))
    return path


def test_the_truth_rides_beside_the_controller_inputs_to_the_ground():
    cap = Capture()
    Telemetry(cap).deorbit_attitude(5.0, AttitudeReport(0.1, 0.2, 0.3, (0, 0, 0), (0.01, 0.02), 0.0, TRUSTED, 1),
                                    held=0, truth_ypr=(0.11, 0.18, 0.3))
    dec = Decoder()
    dec.handle(cap.messages()[0], 0.0)
    assert dec.deorbit_attitude["truth_ypr_rad"] == pytest.approx((0.11, 0.18, 0.3), rel=1e-6)
    cap = Capture()
    Telemetry(cap).deorbit_attitude(5.0, AttitudeReport(), held=0)  # the target: no truth
    dec.handle(cap.messages()[0], 0.0)
    assert all(math.isnan(x) for x in dec.deorbit_attitude["truth_ypr_rad"])


def test_the_tool_scores_the_trusted_inputs_and_writes_plot_and_csv(tmp_path, capsys):
    rows = [(float(t), (0.10 + 0.03 * (-1) ** t, -0.2, 0.0), (0.10, -0.2 + 0.04, 0.0), TRUSTED) for t in range(20)]
    rows += [(20.0 + t, (2.0, 2.0, 0.0), (0.1, 0.1, 0.0), UNTRUSTED) for t in range(5)]  # not scored
    log = _tlog(tmp_path / "run.tlog", rows)
    png, out_csv = tmp_path / "a.png", tmp_path / "a.csv"
    assert deorbit_attitude.main([str(log), "--plot", str(png), "--csv", str(out_csv)]) == 0
    out = capsys.readouterr().out
    assert "25 DEBRIS_DEORBIT_ATTITUDE, 20 trusted" in out and "yaw 0.030 rad, pitch 0.040 rad" in out
    assert png.stat().st_size > 10_000
    table = list(csv.DictReader(out_csv.open()))
    assert len(table) == 25 and float(table[0]["true_pitch_rad"]) == pytest.approx(-0.16, rel=1e-6)
    assert table[-1]["trusted"] == "0"


def test_errors_are_one_line(tmp_path, capsys):
    assert deorbit_attitude.main([str(tmp_path / "missing.tlog")]) == 1
    assert capsys.readouterr().err.count("\n") == 1
    other = tmp_path / "other.tlog"
    cap = Capture()
    cap.mav.heartbeat_send(6, 8, 0, 0, 4)
    other.write_bytes(b"".join(tlog_record(m, 1_750_000_000.0) for m in cap.messages()))
    assert deorbit_attitude.main([str(other)]) == 1
    assert "no DEBRIS_DEORBIT_ATTITUDE" in capsys.readouterr().err
    junk = tmp_path / "junk.tlog"
    junk.write_bytes(b"not a tlog at all")
    assert deorbit_attitude.main([str(junk)]) == 1
