"""Nothing lost to a lossy link: the box numbers its samples and keeps them, the ground sees the gaps,
asks for them (a signed DEBRIS_SAMPLE_REQUEST) and ends with a complete recording, in order."""
import numpy as np

from fsw.flight import FlightSoftware
from fsw.telemetry.dialect import FSW_COMPID, FSW_SYSID, mavlink
from fsw.telemetry.framing import Deframer
from fsw.telemetry.sample_store import SampleStore
from fsw.telemetry.signing import SigningClock, unix_clock, unix_to_timestamp
from fsw.telemetry.telemetry import Telemetry
from ground.command import GroundLink
from ground.decode import Decoder
from ground.gaps import GapRequester, SeqGaps
from ground.recorder import Recorder
from ground.recording import read_recording
from hil.faults import FaultyLink
from support import StubSource


UNIX0 = 1_750_000_000.0
KEY = bytes(range(40, 72))


def test_seq_gaps_watermark_missing_and_giving_up():
    g = SeqGaps()
    for s in (5, 6, 9, 10):
        assert g.add(s)
    assert not g.add(6)                                   # a duplicate
    assert g.watermark == 7 and g.missing() == [7, 8]
    g.extend(13)                                          # the box says 11, 12 exist too
    assert g.missing() == [7, 8, 11, 12]
    g.give_up([7])
    assert g.watermark == 8
    assert g.add(7) and g.filled_late == 1                # given up, then it came after all
    g.start_at(3)                                         # the run began just before the first that arrived
    assert g.watermark == 3 and g.missing() == [3, 4, 8, 11, 12]
    assert g.add(10**7) and g.strays == 1 and g.end == 13  # a forged far-off number: no gap of millions


def test_requester_holds_then_asks_then_retries_then_gives_up():
    g = SeqGaps()
    g.add(0), g.add(4)
    r = GapRequester(hold_s=1.0, retry_s=2.0, max_attempts=2)
    assert r.due(g, 0.0) == []                            # first seen missing: let reordering settle
    assert r.due(g, 1.0) == [(1, 3)]
    assert r.due(g, 2.0) == []                            # not again before retry_s
    assert r.due(g, 3.0) == [(1, 3)]
    assert r.due(g, 5.0) == [] and g.missing() == [] and r.given_up == 3
    g2 = SeqGaps()
    g2.add(0), g2.add(10)
    assert r.due(g2, 0.0, stored_first_seq=5) == [] and g2.missing() == [5, 6, 7, 8, 9]   # 1..4 gone from the box


def fly(seconds, *, loss=0.3, lossy=(5.0, 25.0), key=KEY, tmp_path=None, requests=True, seed=3):
    """The flight software (10 Hz samples, 50 Hz loop) and a ground decoder over an in-memory radio
    that loses `loss` of the frames both ways during `lossy`."""
    rng = np.random.default_rng(seed)
    link = FaultyLink(rng, src_system=FSW_SYSID, src_component=FSW_COMPID)
    clock = SigningClock(epoch=unix_to_timestamp(UNIX0), clock_set=True)
    tlm = Telemetry(link, key=key, clock=clock)
    fsw = FlightSoftware(StubSource(0.1), tlm, rate_hz=50.0, sigma_b_T=0.05e-6, sample_rate_hz=10.0,
                         uplink=link, key=key, sample_store=SampleStore(run_id=0xABCD))
    recorder = Recorder(tmp_path / "run.csv", None) if tmp_path is not None else None
    ask = GroundLink(link.ground_write, key, unix_clock(), link_id=2) \
        if requests else None
    dec = Decoder(key=key, recorder=recorder, requests=ask)
    deframer = Deframer()
    for k in range(int(seconds * 50)):
        t = k / 50
        link.loss = loss if lossy[0] <= t < lossy[1] else 0.0
        fsw.tick(t)
        if k % 5 == 0:
            for m in deframer.feed(link.ground_read()):
                dec.handle(m, UNIX0 + t)
            dec.tick(UNIX0 + t)
    dec.finish()
    return fsw, dec, link


def test_a_lossy_link_loses_no_sample_the_ground_asks_for_them_again(tmp_path):
    fsw, dec, link = fly(60.0, tmp_path=tmp_path)
    assert link.truth["frames_lost"] > 50                              # the link did lose frames
    rep = dec.sample_report()
    assert rep["samples"] == fsw.tlm_samples == 600 and rep["missing"] == 0 and rep["late"] > 10
    assert dec.requests_sent > 0 and fsw.resender.resent >= rep["late"]
    rec = read_recording(tmp_path / "run.csv")                         # complete and in order on disk
    np.testing.assert_allclose(rec.t_s, np.arange(600) * 0.1, atol=1e-9)
    assert fsw.uplink.counters.unsigned == 0                           # the requests were signed


def test_without_requests_the_lost_samples_are_reported_missing(tmp_path):
    fsw, dec, link = fly(40.0, tmp_path=tmp_path, requests=False)
    rep = dec.sample_report()
    assert rep["missing"] > 0 and rep["samples"] + rep["missing"] == fsw.tlm_samples
    rec = read_recording(tmp_path / "run.csv")                         # what arrived, in order
    assert len(rec) == rep["samples"] and (np.diff(rec.t_s) > 0).all()


def test_unsigned_requests_are_refused_by_a_box_with_a_key():
    rng = np.random.default_rng(0)
    link = FaultyLink(rng, src_system=FSW_SYSID, src_component=FSW_COMPID)
    clock = SigningClock(epoch=unix_to_timestamp(UNIX0), clock_set=True)
    fsw = FlightSoftware(StubSource(0.1), Telemetry(link, key=KEY, clock=clock), rate_hz=50.0, sigma_b_T=0.05e-6,
                         sample_rate_hz=10.0, uplink=link, key=KEY)
    stranger = GroundLink(link.ground_write, None)
    for k in range(100):
        fsw.tick(k / 50)
    stranger.send(mavlink.MAVLink_debris_sample_request_message(FSW_SYSID, FSW_COMPID, 0, 5), UNIX0)
    fsw.tick(2.0)
    assert fsw.resender.requests == 0 and fsw.uplink.counters.unsigned == 1
