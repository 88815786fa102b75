"""Store and forward: frames kept while the link is down, replayed in order within the budget when it
returns; the ground merges the replayed samples by time and says what is missing; loss counting across
gaps of 256 frames or more."""
import math

import numpy as np
import pytest

from fsw.flight import FlightSoftware
from fsw.telemetry.dialect import FSW_COMPID, FSW_SYSID, mavlink
from fsw.telemetry.framing import Deframer
from fsw.telemetry.store_forward import FrameRing, StoreForward, stored
from fsw.telemetry.telemetry import Telemetry
from ground.decode import Decoder
from ground.link_stats import LinkStats
from hil.faults import FaultyLink


def test_ring_is_fifo_and_drops_the_oldest_when_full():
    r = FrameRing(3)
    for k in range(5):
        r.push(k)
    assert len(r) == 3 and r.dropped == 2 and r.capacity == 3
    assert [r.pop() for _ in range(4)] == [2, 3, 4, None]
    with pytest.raises(ValueError):
        FrameRing(0)


def test_only_data_products_are_kept():
    assert stored(mavlink.MAVLink_debris_mag_sample_message(0, 0, 0, [0, 0, 0], 0))
    assert stored(mavlink.MAVLink_debris_rate_estimate_message(0, 0, 0, 0, 0, 0, 0, 1, 0))
    assert not stored(mavlink.MAVLink_heartbeat_message(0, 0, 0, 0, 0, 3))
    assert not stored(mavlink.MAVLink_debris_loop_status_message(0, 0, 0, 0, 0, 0, 0, 0, 0))


class Source:
    """A field turning about z at 0.1 rad/s, sampled at 10 Hz."""

    def __init__(self):
        self.b_body_T = np.zeros(3)
        self.sample_time_s = math.nan
        self.k = 0

    def update(self, now_s):
        if now_s + 1e-9 < self.k * 0.1:
            return False
        t = self.sample_time_s = self.k * 0.1
        self.b_body_T = 40e-6 * np.array([math.cos(0.1 * t), math.sin(0.1 * t), 0.5])
        self.k += 1
        return True


def fly(outages, seconds=60.0, capacity=4096, replay_bytes_per_s=2500.0):
    """Flight software at 50 Hz on a link that is unplugged during `outages` [(start, end)], a ground
    decoder at the other end. Returns (fsw, decoder, link, bytes replayed per tick)."""
    link = FaultyLink(np.random.default_rng(0), src_system=FSW_SYSID, src_component=FSW_COMPID)
    store = StoreForward(capacity, replay_bytes_per_s=replay_bytes_per_s)
    fsw = FlightSoftware(Source(), Telemetry(link, store=store), rate_hz=50, sigma_b_T=1e-8, sample_rate_hz=10)
    dec, deframer = Decoder(), Deframer()
    replay_per_tick = []
    for k in range(int(seconds * 50)):
        t = k / 50
        down = any(a <= t < b for a, b in outages)
        if down and link.connected:
            link.disconnect()
        elif not down and not link.connected:
            link.reconnect()
        before = store.replayed_bytes
        fsw.tick(t)
        data = link.ground_read()
        replay_per_tick.append(store.replayed_bytes - before)
        for msg in deframer.feed(data):
            dec.handle(msg, t)
    return fsw, dec, link, replay_per_tick


def test_a_short_outage_loses_no_sample():
    fsw, dec, link, _ = fly([(10.0, 25.0)])
    store = fsw.tlm.store
    assert store.outages == 1 and store.stored > 0 and store.replayed == store.stored and store.buffered == 0
    assert store.dropped == 0 and store.skipped > 0            # status messages were not kept
    rec = dec.recording()
    np.testing.assert_allclose(rec.t_s, np.arange(fsw.tlm_samples) * 0.1, atol=1e-9)   # all, in time order
    rep = dec.sample_report()
    assert rep["missing"] == 0 and rep["late"] > 100 and len(dec.segments) == 1
    stats = dec.stats.summary()["totals"]
    assert stats["lost"] == 0                                  # replays go out with fresh sequence numbers
    assert "none missing" in dec.summary_text() and "sent again after an outage" in dec.summary_text()
    est = dec.rate_estimates()
    assert np.isfinite(est.w_radps[2:]).all()                  # the replayed estimates are merged too


def test_replay_stays_within_its_budget_and_never_blocks_live_telemetry():
    budget = 1000.0
    fsw, dec, link, per_tick = fly([(5.0, 20.0)], seconds=60.0, replay_bytes_per_s=budget)
    replayed = np.array(per_tick)
    assert replayed.sum() == fsw.tlm.store.replayed_bytes > 3 * budget    # several seconds of replay
    # in any second after the link returns: at most the budget, plus the one frame that overdraws it
    window = np.convolve(replayed, np.ones(50), mode="valid")
    assert window.max() <= budget + 100
    # live samples went out during the replay: their times reached the ground in order, on time
    live = [t for t in dec.recording().t_s if t >= 20.0]
    assert len(live) == 400
    assert dec.sample_report()["missing"] == 0


def test_an_outage_longer_than_the_buffer_is_reported_as_a_gap():
    fsw, dec, link, _ = fly([(10.0, 40.0)], capacity=200)
    store = fsw.tlm.store
    assert store.dropped > 0
    rep = dec.sample_report()
    assert rep["missing"] > 0 and len(rep["gaps"]) == 1
    a, b, k = rep["gaps"][0]
    assert 10.0 - 0.2 <= a and b <= 40.0 + 0.2            # the oldest samples of the outage are the ones lost
    assert "missing in 1 gaps" in dec.summary_text()


def test_replayed_samples_are_not_mistaken_for_a_restart_and_a_restart_is_still_seen():
    dec = Decoder()
    p = mavlink.MAVLink(None, srcSystem=FSW_SYSID, srcComponent=FSW_COMPID)
    parser = mavlink.MAVLink(None)

    def send(msg):
        frame = msg.pack(p)
        p.seq = (p.seq + 1) % 256
        for m in parser.parse_buffer(frame):
            dec.handle(m, 0.0)

    def imu(t_s):
        send(mavlink.MAVLink_highres_imu_message(int(t_s * 1e6), 0, 0, 0, 0, 0, 0, 0.4, 0, 0, 0, 0, 0, 0, 0x1C0))

    def loop(t_s, ticks):
        send(mavlink.MAVLink_debris_loop_status_message(int(t_s * 1e6), ticks, 0, 0, 2e4, 0, 0, 0, 0))

    for t in range(0, 10):
        imu(t)
        loop(t + 0.5, 50 * t)
    for t in range(30, 40):                      # outage 10..29 s: live again ...
        imu(t)
        loop(t + 0.5, 50 * t)
    for t in range(10, 30):                      # ... then the replay, 20 s old
        imu(t)
    assert len(dec.segments) == 1 and dec.sample_report()["missing"] == 0 and dec.sample_report()["late"] == 20
    # restart: the loop time goes back to 0; the new run's first sample (t=0, before its first
    # LOOP_STATUS) goes to the new run
    imu(0.0)
    loop(0.5, 25)
    imu(1.0)
    assert len(dec.segments) == 2
    np.testing.assert_allclose(dec.recording().t_s, [0.0, 1.0])
    np.testing.assert_allclose(sorted(dec.segments[0].mag_gauss), np.arange(1, 40) * 1e6)


def test_loss_of_more_than_255_frames_is_counted_from_the_senders_frame_count():
    """The 8-bit sequence number reads a gap of 300 frames as 44; DEBRIS_LINK_STATUS frames_sent
    gives the true number."""
    p = mavlink.MAVLink(None, srcSystem=FSW_SYSID, srcComponent=FSW_COMPID)
    parser = mavlink.MAVLink(None)
    stats = LinkStats()
    sent = 0

    def send(msg, deliver=True):
        nonlocal sent
        sent += 1
        if isinstance(msg, mavlink.MAVLink_debris_link_status_message):
            msg.frames_sent = sent
        frame = msg.pack(p)
        p.seq = (p.seq + 1) % 256
        if deliver:
            for m in parser.parse_buffer(frame):
                stats.on_frame(m, 0.0)
                if m.get_type() == "DEBRIS_MAG_SAMPLE" and stats.last_verdict != "new":
                    raise AssertionError(stats.last_verdict)

    def status():
        return mavlink.MAVLink_debris_link_status_message(0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 0)

    imu = mavlink.MAVLink_highres_imu_message(0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    for _ in range(20):
        send(imu)
    send(status())
    for _ in range(300):
        send(imu, deliver=False)                  # 300 frames lost
    for _ in range(10):
        send(imu)
    assert stats.lost() == 300 % 256              # what the sequence number alone can say
    send(status())
    assert stats.lost() == 300
    s = stats.summary()["sources"][(FSW_SYSID, FSW_COMPID)]
    assert s["hidden_gaps"] == 1 and s["received"] == 32
    # a duplicate is not a loss (pymavlink's own counter calls it 255 lost frames)
    frame = imu.pack(p)
    p.seq = (p.seq + 1) % 256
    for _ in range(2):
        for m in parser.parse_buffer(frame):
            stats.on_frame(m, 0.0)
    assert stats.lost() == 300 and stats.summary()["totals"]["duplicates"] == 1
