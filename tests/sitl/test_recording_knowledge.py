"""SITL on an SGP4 orbit with the box's clock 2 s off: the decoder's recording carries the box's TLE (the
scenario's older `box_tle`, not the truth's) and the UTC of the box's t = 0 — the simulated world's utc0
moved by the clock's offset — and the field the ground computes from that metadata is the box's."""
import dataclasses
import io
from datetime import datetime, timezone

import numpy as np
import pytest

from fsw.config import RunConfig
from fsw.estimation.onboard_field import field_from_metadata
from fsw.telemetry.dialect import mavlink
from ground.decode import Decoder
from ground.recorder import Recorder
from ground.recording import read_recording
from hil import scenario, sitl
from hil.box_clock import BoxClock

pytestmark = pytest.mark.sitl


class Capture:
    def __init__(self):
        self.mav = mavlink.MAVLink(self, srcSystem=1, srcComponent=191)
        self.data = bytearray()

    def write(self, b):
        self.data += b


def test_the_recording_of_a_sgp4_run_holds_the_box_s_tle_and_the_utc_of_its_t0(tmp_path):
    scn = dataclasses.replace(scenario.load("isoi_sgp4"), clock=BoxClock(offset_s=2.0, drift_ppm=20.0))
    link = Capture()
    run = sitl.run(sitl.SitlConfig(run=RunConfig(speed=0.0, duration_s=65.0, quiet=True), scenario=scn),
                   out=io.StringIO(), link=link)
    assert run.loop.t_s > 65.0
    dec = Decoder(recorder=Recorder(tmp_path / "run.csv", None))
    parser = mavlink.MAVLink(None)
    for i, m in enumerate(parser.parse_buffer(bytes(link.data)) or []):
        dec.handle(m, 1000.0 + i * 1e-3)
    dec.finish()
    rec = read_recording(tmp_path / "run.csv")
    md = rec.metadata
    assert (md["tle_line1"], md["tle_line2"]) == tuple(scn.box_tle) and md["tle_state"] == "ok"
    assert md["field_model"].startswith("igrf14:")
    utc0_true = scn.utc0.replace(tzinfo=timezone.utc).timestamp()
    # the box's clock reads 2 s at the world's utc0: its t = 0 is 2 s earlier
    assert datetime.fromisoformat(md["utc0"]).timestamp() == pytest.approx(utc0_true - 2.0, abs=1e-3)
    assert rec.t_s[0] >= 2.0
    # the ground's field from the metadata is the box's own field model along its TLE at its UTC
    ground = field_from_metadata(md)
    box = run.sitl.flight.timeorbit.field_now(run.loop.t_s)[0]
    t = np.array([10.0, 30.0, 60.0])
    np.testing.assert_allclose(ground.b_eci_T(t), box.b_eci_T(t), atol=5e-9)    # within 5 nT
