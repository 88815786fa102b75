"""Faults injected in `hil/` and survived in `fsw/`: the sample gate, estimates across gaps, every
magnetometer fault against the real driver in lockstep SITL, and every link fault against the ground's
framing and loss accounting (checked against what the faulty link really did)."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fsw.estimation import rate_formulas as rf
from fsw.estimation.rate_formulas import SIGMA_UNOBSERVED_RADPS
from fsw.estimation.sample_gate import FULL_SCALE_T, SampleGate, gap_sigma_factor
from fsw.flight import FlightSoftware
from fsw.config import RunConfig
from hil import sitl
from fsw.telemetry.dialect import FSW_COMPID, FSW_SYSID, mavlink
from fsw.telemetry.framing import Deframer
from fsw.telemetry.telemetry import Telemetry
from ground.decode import Decoder
from hil.faults import ALL_KINDS, LINK_KINDS, MAG_KINDS, Fault, FaultInjector, FaultyLink, make_schedule

W_RADPS = np.radians([6.0, -5.0, 6.5])
B_I_T = np.array([20e-6, -15e-6, 35e-6])
SIGMA_T = 0.1e-6


def tumbling(n, dt=1.0, seed=0):
    """Field samples of a body tumbling at W (dB/dt = B × ω), with noise σ."""
    t = np.arange(n) * dt
    b = np.array([Rotation.from_rotvec(-W_RADPS * tk).apply(B_I_T) for tk in t])
    return t, b + np.random.default_rng(seed).normal(0, SIGMA_T, b.shape)


# --- the gate -----------------------------------------------------------------------------------
def test_gate_accepts_a_clean_tumbling_body():
    g = SampleGate(SIGMA_T, 1.0)
    t, b = tumbling(2000)
    assert all(g.check(tk, bk) for tk, bk in zip(t, b))
    assert g.rejected == 0 and g.gap_samples == 0


@pytest.mark.parametrize("kind", ["saturated", "stuck", "spike", "non_finite"])
def test_gate_refuses_and_names_each_kind(kind):
    g = SampleGate(SIGMA_T, 1.0)
    t, b = tumbling(20)
    bad = b.copy()
    if kind == "saturated":
        bad[10, 1] = -FULL_SCALE_T                         # clipped at -8 G
    elif kind == "stuck":
        bad[10] = bad[9]                                   # the same 18-bit reading twice
    elif kind == "spike":
        bad[10] += [0, 0, 30e-6]                           # |B| jumps by ~30 µT in 1 s
    else:
        bad[10, 0] = np.nan
    ok = [g.check(tk, bk) for tk, bk in zip(t, bad)]
    assert ok.count(False) == 1 and not ok[10]
    assert g.counts[kind] == 1 and g.rejected == 1
    assert g.gap_samples == 0 and ok[11]
    # the sample after the refused one knows that one is missing before it
    g2 = SampleGate(SIGMA_T, 1.0)
    for k in range(12):
        g2.check(t[k], bad[k])
        if k == 11:
            assert g2.gap_samples == 1


def test_gate_moves_its_reference_after_repeated_spikes():
    """If the reference itself was the bad sample (or the motion changed), the gate does not refuse
    forever."""
    g = SampleGate(SIGMA_T, 1.0, reseed_after=3)
    t, b = tumbling(12)
    b[5:] += [0, 0, 30e-6]                                   # a lasting step, e.g. a magnet moved
    ok = [g.check(tk, bk) for tk, bk in zip(t, b)]
    assert ok[:5] == [True] * 5 and ok[5:8] == [False] * 3 and all(ok[8:])


def test_gate_reference_follows_a_new_calibration():
    """A calibration moves every sample by its hard iron: re-expressed in it, the reference does not make
    the first calibrated sample a spike; the chip's own output still decides saturation."""
    t, b = tumbling(12)
    hard_T = np.array([30e-6, -20e-6, 25e-6])
    for rebase, want in ((False, [False] * 3), (True, [True] * 3)):
        g = SampleGate(SIGMA_T, 1.0, reseed_after=3)
        assert all(g.check(tk, bk + hard_T) for tk, bk in zip(t[:5], b[:5]))  # raw: the iron in it
        if rebase:
            g.rebase(b[4])                                    # the same sample, calibrated
        assert [g.check(tk, bk + hard_T, bk) for tk, bk in zip(t[5:8], b[5:8])] == want
    g = SampleGate(SIGMA_T, 1.0)
    assert g.check(0.0, np.array([FULL_SCALE_T, 0, 0]), np.array([20e-6, 0, 0])) is False
    assert g.counts["saturated"] == 1


def test_estimates_across_a_refused_sample_are_flagged_and_widened():
    class Replay:
        def __init__(self, t, b):
            self.t, self.b, self.k = t, b, 0
            self.b_body_T, self.sample_time_s = np.zeros(3), math.nan

        def update(self, now_s):
            if self.k >= len(self.t) or now_s + 1e-9 < self.t[self.k]:
                return False
            self.sample_time_s, self.b_body_T = self.t[self.k], self.b[self.k]
            self.k += 1
            return True

    class Null:
        def __init__(self):
            self.mav = mavlink.MAVLink(self, srcSystem=1, srcComponent=191)

        def write(self, b):
            pass

    t, b = tumbling(40)
    b[10] = b[9]                     # stuck once: refused
    b[20:28] = b[19]                 # stuck for eight samples: a long gap, the estimators start afresh
    fsw = FlightSoftware(Replay(t, b), Telemetry(Null()), rate_hz=10, sigma_b_T=SIGMA_T, sample_rate_hz=1)
    seen = {}
    for k in range(400):
        fsw.tick(k / 10)
        if fsw.new_sample:
            seen[round(fsw.sample_t_s)] = {n: (e.flags, e.sigma_radps.copy()) for n, e in fsw.estimators.items()}
    gap = mavlink.DEBRIS_ESTIMATE_FLAGS_DATA_GAP
    assert fsw.gate.counts["stuck"] == 9
    assert seen[11]["boer"][0] & gap and seen[11]["derivative"][0] & gap
    assert not seen[12]["boer"][0] & gap and seen[12]["derivative"][0] & gap   # 3 samples span it twice
    assert not seen[13]["derivative"][0] & gap
    # σ of the Boer formula over the 2 s step (first-order propagation), times the gap factor
    sigma = np.sqrt(np.diag(rf.boer_covariance(t[[9, 11]], b[[9, 11]], SIGMA_T)[1]))
    np.testing.assert_allclose(seen[11]["boer"][1], np.minimum(sigma * gap_sigma_factor(1), SIGMA_UNOBSERVED_RADPS),
                               rtol=1e-6)
    assert seen[28]["boer"][0] & mavlink.DEBRIS_ESTIMATE_FLAGS_NO_ESTIMATE     # after 8 missing: afresh
    assert not seen[30]["boer"][0] & (gap | mavlink.DEBRIS_ESTIMATE_FLAGS_NO_ESTIMATE)


# --- the schedule -------------------------------------------------------------------------------
def test_schedule_is_seeded_sequential_and_covers_every_kind():
    a = make_schedule(np.random.default_rng(5), 3600.0)
    assert a == make_schedule(np.random.default_rng(5), 3600.0)
    assert a != make_schedule(np.random.default_rng(6), 3600.0)
    assert {f.kind for f in a} == set(ALL_KINDS)
    assert all(f.end_s < g.start_s for f, g in zip(a, a[1:]))
    assert a[0].start_s == 30.0 and a[-1].end_s <= 3600.0 - 60.0


# --- magnetometer faults against the driver, in lockstep SITL ------------------------------------
class Null:
    def __init__(self):
        self.mav = mavlink.MAVLink(self, srcSystem=FSW_SYSID, srcComponent=FSW_COMPID)

    def write(self, b):
        pass


def sys_status_health(fsw):
    return (not fsw.gate.rejecting) and int(fsw.source.state) == mavlink.DEBRIS_MAG_STATE_MEASURE


@pytest.mark.parametrize("kind", MAG_KINDS)
def test_each_magnetometer_fault_is_flagged_and_survived(kind):
    # the shipped scenario's world: IGRF, the host's iron not yet calibrated (the gate allows for it)
    box = sitl.build(sitl.SitlConfig(RunConfig(rate_hz=50.0, buffer_frames=0), seed=2,
                                     scenario="isoi"), link=Null(), ident=False)
    sim, driver, fsw = box.sim, box.driver, box.fsw
    severity = {"bus_errors": 1.0, "spike": 100e-6, "saturation": 1.1e-3}.get(kind, 0.0)
    duration = 0.0 if kind in ("spike", "chip_reset") else 5.0
    fault = Fault(kind, 10.3, duration, severity)
    inj = FaultInjector([fault], sim.sensor, FaultyLink(np.random.default_rng(0), src_system=1, src_component=1),
                        np.random.default_rng(1), sample_period_s=1.0)
    unhealthy = 0
    accepted_at_end = None
    for k in range(int(30 * 50)):
        t = k / 50
        for what, _ in inj.update(t):
            if what == "end":
                accepted_at_end = fsw.gate.accepted
        sim.advance_to(t)
        fsw.tick(t)
        if fault.start_s < t < fault.end_s + 2:
            unhealthy += not sys_status_health(fsw)
    flagged = {
        "no_data_ready": driver.timeouts > 0, "bus_errors": driver.bus_errors > 0,
        "stuck": fsw.gate.counts["stuck"] > 0, "spike": fsw.gate.counts["spike"] > 0,
        "saturation": fsw.gate.counts["saturated"] > 0, "chip_reset": driver.chip_resets_detected > 0,
        "wrong_id": driver.bad_id > 0,
    }[kind]
    assert flagged
    assert fsw.scheduler.stats.ticks == 1500                       # the loop never stopped
    assert int(driver.state) == mavlink.DEBRIS_MAG_STATE_MEASURE   # recovered ...
    assert fsw.gate.accepted >= accepted_at_end + 10              # ... and delivering good samples again
    assert fsw.gate.accepted + fsw.gate.rejected == fsw.samples
    if kind in ("stuck", "saturation", "no_data_ready", "bus_errors", "wrong_id"):
        assert unhealthy > 0                                         # SYS_STATUS showed it


# --- link faults against the ground --------------------------------------------------------------
def stream(link, kind, n):
    """A clean frame, n HIGHRES_IMU frames (one per 0.1 s) through the link with the fault on, a clean
    frame (so that losses at either end are visible); the ground's decoder and frame count."""
    p = link.mav
    dec, deframer = Decoder(), Deframer()
    frames = 0
    for k in range(n + 2):
        setattr(link, kind, 0.3 if 0 < k <= n else 0.0)
        if k == n + 1:
            link.flush_held()
        msg = mavlink.MAVLink_highres_imu_message(k * 100_000, 0, 0, 0, 0, 0, 0, 0.3, 0.1, -0.2, 0, 0, 0, 0, 0x1C0)
        link.write(msg.pack(p))
        p.seq = (p.seq + 1) % 256
        for m in deframer.feed(link.ground_read()):
            dec.handle(m, k * 0.1)
            frames += m.get_type() != "BAD_DATA"
    for m in deframer.flush():
        dec.handle(m, n * 0.1)
        frames += m.get_type() != "BAD_DATA"
    return dec, frames


@pytest.mark.parametrize("kind", ["loss", "corruption", "garbage", "duplicates", "reordering"])
def test_each_link_fault_is_accounted_exactly(kind):
    link = FaultyLink(np.random.default_rng(3), src_system=FSW_SYSID, src_component=FSW_COMPID)
    dec, frames = stream(link, kind, 2000)
    truth = link.truth
    totals = dec.stats.summary()["totals"]
    assert truth[{"loss": "frames_lost", "corruption": "frames_lost", "garbage": "garbage_bytes",
                  "duplicates": "frames_duplicated", "reordering": "frames_reordered"}[kind]] > 100
    assert frames == truth["frames_delivered_intact"]          # every intact frame decoded (the tlog's content)
    assert totals["lost"] == truth["frames_lost"]              # loss per source, exactly
    assert totals["duplicates"] == truth["frames_duplicated"]
    if kind == "reordering":
        assert totals["late"] == truth["frames_reordered"]
    if kind == "garbage":
        assert dec.stats.garbage_bytes == truth["garbage_bytes"]
    rep = dec.sample_report()
    assert rep["samples"] == 2002 - truth["frames_lost"]
    assert rep["missing"] == truth["frames_lost"]


def test_disconnect_cuts_a_frame_and_the_ground_resyncs():
    link = FaultyLink(np.random.default_rng(4), src_system=FSW_SYSID, src_component=FSW_COMPID)
    p = link.mav
    out = []
    deframer = Deframer()
    cut = 0
    for k in range(200):
        link.write(mavlink.MAVLink_heartbeat_message(0, 0, 0, 0, 0, 3).pack(p))
        p.seq = (p.seq + 1) % 256
        if k % 20 == 10:                    # the port goes away with the frame still on its way
            before = link.truth["frames_lost"]
            link.disconnect()
            cut += link.truth["frames_lost"] - before
            with pytest.raises(OSError):
                link.write(b"\xfd")
            link.reconnect()
        out += [m for m in deframer.feed(link.ground_read()) if m.get_type() == "HEARTBEAT"]
    assert cut > 0 and len(out) == 200 - cut


def test_link_kinds_are_all_tested():
    assert set(LINK_KINDS) == {"loss", "corruption", "garbage", "duplicates", "reordering", "disconnect"}
