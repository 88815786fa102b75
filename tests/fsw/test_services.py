"""MAVLink services through the real uplink path (flight software on an in-memory radio link, a ground
station at the other end): what ground software asks, what the box answers, signed and unsigned, and
what a flood of requests costs."""
import struct

import numpy as np
import pytest

from fsw.flight import FlightSoftware
from fsw.telemetry.dialect import FSW_COMPID, FSW_SYSID, GCS_COMPID, GCS_SYSID, mavlink
from fsw.telemetry.services import BOX_MESSAGES, MIN_INTERVAL_S, version_word
from fsw.telemetry.signing import SigningClock, Verdict, unix_to_timestamp
from fsw.telemetry.store_forward import StoreForward
from fsw.telemetry.telemetry import Telemetry
from ground.command import GroundLink
from hil.faults import FaultyLink
from support import SteadySource

KEY = bytes(range(100, 132))
T0 = unix_to_timestamp(1_750_000_000.0)
R = mavlink
RATE_HZ = 10


class Box:
    """Flight software (10 Hz loop) on an in-memory link; `ground` signs with the key, `stranger` does not."""

    def __init__(self, key=KEY):
        self.link = FaultyLink(np.random.default_rng(0), src_system=FSW_SYSID, src_component=FSW_COMPID)
        tlm = Telemetry(self.link, store=StoreForward(), key=key, clock=SigningClock(epoch=T0, clock_set=True))
        self.fsw = FlightSoftware(SteadySource(), tlm, rate_hz=RATE_HZ, sigma_b_T=1e-7, sample_rate_hz=1.0,
                                  uplink=self.link, key=key)
        self.runs = []
        self.fsw.commands.register(R.MAV_CMD_USER_1, lambda m, t: self.runs.append((m.param1, m.param5)))
        self.fsw.commands.register(R.MAV_CMD_USER_2, lambda m, t: None, long_only=True)
        self.ground = GroundLink(self.link.ground_write, key, SigningClock(epoch=T0, clock_set=True))
        self.stranger = GroundLink(self.link.ground_write, None)
        self.k = 0
        self.received = []

    @property
    def now(self):
        return self.k / RATE_HZ

    def run(self, seconds):
        """Run the loop; returns what the ground received meanwhile (only what verified, with a key)."""
        start = len(self.received)
        for _ in range(int(round(seconds * RATE_HZ))):
            self.fsw.tick(self.now)
            self.k += 1
            self.received += [r for r in self.ground.feed(self.link.ground_read(), self.now)
                              if r.verdict in (None, Verdict.OK)]
        return [r.msg for r in self.received[start:]]

    def command(self, command, *params, link=None, target=(FSW_SYSID, FSW_COMPID)):
        (link or self.ground).command_long(command, params, self.now, target=target)

    def command_int(self, command, p1=0.0, x=0, y=0, z=0.0, link=None, target=(FSW_SYSID, FSW_COMPID)):
        (link or self.ground).send(mavlink.MAVLink_command_int_message(
            target[0], target[1], 0, command, 0, 0, p1, 0, 0, 0, x, y, z), self.now)


def of(msgs, kind):
    return [m for m in msgs if m.get_type() == kind]


def acks(msgs):
    return [(m.command, m.result) for m in of(msgs, "COMMAND_ACK")]


# --- what a stock ground station needs to see a vehicle ------------------------------------------------
def test_the_heartbeat_is_a_vehicle_for_a_ground_station():
    """MAVProxy (mavproxy_link.heartbeat_is_from_autopilot) never shows a heartbeat with autopilot
    MAV_AUTOPILOT_INVALID or RESERVED as a vehicle ("online"): the box's is neither, nor a GCS's."""
    box = Box()
    hb = of(box.run(1.0), "HEARTBEAT")[0]
    assert hb.autopilot not in (R.MAV_AUTOPILOT_INVALID, R.MAV_AUTOPILOT_RESERVED)
    assert hb.type == R.MAV_TYPE_SPACECRAFT_ORBITER and hb.get_srcComponent() == FSW_COMPID


@pytest.mark.parametrize("signed", [True, False])
def test_ping_is_mirrored_to_its_sender_and_a_ping_answer_is_not_answered(signed):
    box = Box()
    box.run(0.5)
    link = box.ground if signed else box.stranger
    link.send(mavlink.MAVLink_ping_message(123456789, 42, 0, 0), box.now)
    pings = of(box.run(0.3), "PING")
    assert [(p.time_usec, p.seq, p.target_system, p.target_component) for p in pings] == [
        (123456789, 42, GCS_SYSID, GCS_COMPID)]
    # a PING addressed to us is an answer to a ping we never sent: not answered (no ping-pong)
    link.send(mavlink.MAVLink_ping_message(1, 43, FSW_SYSID, FSW_COMPID), box.now)
    assert of(box.run(0.3), "PING") == []


@pytest.mark.parametrize("signed", [True, False])
def test_timesync_request_answered_with_the_box_time_and_ts1_mirrored(signed):
    box = Box()
    box.run(1.0)
    (box.ground if signed else box.stranger).send(mavlink.MAVLink_timesync_message(0, 987654321), box.now)
    sent_at = box.now
    ts = of(box.run(0.3), "TIMESYNC")
    assert len(ts) == 1 and ts[0].ts1 == 987654321
    # no UTC on board (no time application): the box's loop time, read in the tick after the request
    assert abs(ts[0].tc1 * 1e-9 - sent_at) <= 1.0 / RATE_HZ + 1e-9
    # an answer (tc1 != 0) is not answered
    box.ground.send(mavlink.MAVLink_timesync_message(5, 6), box.now)
    assert of(box.run(0.3), "TIMESYNC") == []


def test_autopilot_version_says_only_what_is_true():
    box = Box()
    box.run(0.5)
    box.command(R.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 1)
    box.command(R.MAV_CMD_REQUEST_MESSAGE, R.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
    msgs = box.run(0.5)
    assert acks(msgs) == [(R.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, R.MAV_RESULT_ACCEPTED),
                          (R.MAV_CMD_REQUEST_MESSAGE, R.MAV_RESULT_ACCEPTED)]
    versions = of(msgs, "AUTOPILOT_VERSION")
    assert len(versions) == 2
    caps = versions[0].capabilities
    assert caps == (R.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | R.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                    | R.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT | R.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST)
    assert not caps & (R.MAV_PROTOCOL_CAPABILITY_MISSION_INT | R.MAV_PROTOCOL_CAPABILITY_FTP
                       | R.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE)
    assert version_word("0.1.0") == (0 << 24) | (1 << 16) | (0 << 8) | R.FIRMWARE_VERSION_TYPE_DEV


def test_request_message_for_every_message_the_box_sends():
    box = Box()
    sent = {m.id for m in box.run(3.0)}
    assert sent <= BOX_MESSAGES and len(sent) >= 6  # HEARTBEAT, SYS_STATUS, the status and sample messages
    for mid in sorted(sent):
        box.command(R.MAV_CMD_REQUEST_MESSAGE, mid)
        msgs = box.run(0.1)  # within the tick: before the 1 Hz status sends it again
        assert acks(msgs) == [(R.MAV_CMD_REQUEST_MESSAGE, R.MAV_RESULT_ACCEPTED)], mid
        assert mid in {m.id for m in msgs}, mid
    # a message the box sends but has not yet (no attitude without a filter with one): not now
    box.command(R.MAV_CMD_REQUEST_MESSAGE, R.MAVLINK_MSG_ID_DEBRIS_DEORBIT_STATUS)
    # one it never sends (GPS), and PROTOCOL_VERSION (not in common.xml any more): refused
    box.command(R.MAV_CMD_REQUEST_MESSAGE, R.MAVLINK_MSG_ID_GPS_RAW_INT)
    box.command(R.MAV_CMD_REQUEST_MESSAGE, 300)
    assert acks(box.run(0.3)) == [(R.MAV_CMD_REQUEST_MESSAGE, R.MAV_RESULT_TEMPORARILY_REJECTED),
                                  (R.MAV_CMD_REQUEST_MESSAGE, R.MAV_RESULT_DENIED),
                                  (R.MAV_CMD_REQUEST_MESSAGE, R.MAV_RESULT_DENIED)]
    # SYSTEM_TIME is made fresh: the loop time of the request
    box.command(R.MAV_CMD_REQUEST_MESSAGE, R.MAVLINK_MSG_ID_SYSTEM_TIME)
    at = box.now
    st = of(box.run(0.2), "SYSTEM_TIME")
    assert len(st) == 1 and st[0].time_unix_usec == 0 and abs(st[0].time_boot_ms * 1e-3 - at) <= 0.1 + 1e-9


def test_unknown_commands_are_answered_unsupported_not_silence():
    box = Box()
    box.run(0.5)
    box.command(R.MAV_CMD_NAV_TAKEOFF)
    box.command(R.MAV_CMD_REQUEST_PROTOCOL_VERSION, 1)
    box.command_int(R.MAV_CMD_DO_SET_ROI_LOCATION)
    assert acks(box.run(0.3)) == [(R.MAV_CMD_NAV_TAKEOFF, R.MAV_RESULT_UNSUPPORTED),
                                  (R.MAV_CMD_REQUEST_PROTOCOL_VERSION, R.MAV_RESULT_UNSUPPORTED),
                                  (R.MAV_CMD_DO_SET_ROI_LOCATION, R.MAV_RESULT_UNSUPPORTED)]


@pytest.mark.parametrize("component, answered", [(FSW_COMPID, True), (0, True), (R.MAV_COMP_ID_AUTOPILOT1, True),
                                                 (42, False)])
def test_commands_to_the_system_autopilot_component_are_the_box(component, answered):
    box = Box()
    box.run(0.5)
    box.command(R.MAV_CMD_USER_1, 7, target=(FSW_SYSID, component))
    got = acks(box.run(0.3))
    assert got == ([(R.MAV_CMD_USER_1, R.MAV_RESULT_ACCEPTED)] if answered else [])
    assert box.runs == ([(7.0, 0.0)] if answered else [])
    assert box.fsw.uplink.counters.not_for_us == (0 if answered else 1)


def test_command_int_is_routed_like_command_long():
    box = Box()
    box.run(0.5)
    box.command_int(R.MAV_CMD_USER_1, 3.0, x=12345)
    box.command_int(R.MAV_CMD_USER_2)  # params 5-6 fractional: COMMAND_LONG only
    box.command_int(R.MAV_CMD_REQUEST_MESSAGE, R.MAVLINK_MSG_ID_HEARTBEAT)
    msgs = box.run(0.3)
    assert acks(msgs) == [(R.MAV_CMD_USER_1, R.MAV_RESULT_ACCEPTED), (R.MAV_CMD_USER_2, R.MAV_RESULT_COMMAND_LONG_ONLY),
                          (R.MAV_CMD_REQUEST_MESSAGE, R.MAV_RESULT_ACCEPTED)]
    assert box.runs == [(3.0, 12345.0)] and len(of(msgs, "HEARTBEAT")) == 1
    # unsigned, a state-changing COMMAND_INT is dropped like a COMMAND_LONG
    box.command_int(R.MAV_CMD_USER_1, 4.0, link=box.stranger)
    assert acks(box.run(0.3)) == [] and box.runs == [(3.0, 12345.0)]


def test_unsigned_reads_answered_unsigned_changes_dropped_silently_as_before():
    """Box with a key: a ground station without it sees the box (REQUEST_MESSAGE, parameters) but changes
    nothing, and gets no answer to what would change something (counted as unsigned)."""
    box = Box()
    box.run(0.5)
    s = box.stranger
    box.command(R.MAV_CMD_REQUEST_MESSAGE, R.MAVLINK_MSG_ID_DEBRIS_LINK_STATUS, link=s)
    s.send(mavlink.MAVLink_param_request_list_message(FSW_SYSID, FSW_COMPID), box.now)
    box.command(R.MAV_CMD_SET_MESSAGE_INTERVAL, R.MAVLINK_MSG_ID_HEARTBEAT, 200000, link=s)
    box.command(R.MAV_CMD_USER_1, 9, link=s)
    s.send(mavlink.MAVLink_param_set_message(FSW_SYSID, FSW_COMPID, b"RESEND_BPS", 5.0, R.MAV_PARAM_TYPE_REAL32),
           box.now)
    before = box.fsw.resender.bytes_per_s
    msgs = box.run(0.5)
    assert acks(msgs) == [(R.MAV_CMD_REQUEST_MESSAGE, R.MAV_RESULT_ACCEPTED)]
    assert {p.param_id for p in of(msgs, "PARAM_VALUE")} == set(box.fsw.params.names())
    assert box.runs == [] and box.fsw.resender.bytes_per_s == before
    assert box.fsw.services.rates.streams == {}
    c = box.fsw.uplink.counters
    assert c.unsigned == 3 and c.unsigned_reads == 2  # SET_MESSAGE_INTERVAL, USER_1, PARAM_SET
    assert box.ground.rejected == 0  # the answers are signed like all telemetry, and verified


def test_without_a_key_set_message_interval_is_denied():
    box = Box(key=None)
    box.ground = box.stranger
    box.run(0.5)
    box.command(R.MAV_CMD_SET_MESSAGE_INTERVAL, R.MAVLINK_MSG_ID_HEARTBEAT, 200000)
    box.command(R.MAV_CMD_GET_MESSAGE_INTERVAL, R.MAVLINK_MSG_ID_HEARTBEAT)
    msgs = box.run(0.3)
    assert acks(msgs) == [(R.MAV_CMD_SET_MESSAGE_INTERVAL, R.MAV_RESULT_DENIED),
                          (R.MAV_CMD_GET_MESSAGE_INTERVAL, R.MAV_RESULT_ACCEPTED)]


# --- message rates ------------------------------------------------------------------------------------
def count(msgs, mid):
    return sum(1 for m in msgs if m.id == mid)


def test_set_message_interval_changes_the_rates_counted_over_simulated_time():
    box = Box()
    box.run(1.0)
    hb, loop, store = (R.MAVLINK_MSG_ID_HEARTBEAT, R.MAVLINK_MSG_ID_DEBRIS_LOOP_STATUS,
                       R.MAVLINK_MSG_ID_DEBRIS_SAMPLE_STORE)
    box.command(R.MAV_CMD_SET_MESSAGE_INTERVAL, hb, 200000)      # 5 Hz: faster than its own 1 Hz
    box.command(R.MAV_CMD_SET_MESSAGE_INTERVAL, loop, 5000000)   # every 5 s
    box.command(R.MAV_CMD_SET_MESSAGE_INTERVAL, store, -1)       # off
    assert acks(box.run(1.0)) == [(R.MAV_CMD_SET_MESSAGE_INTERVAL, R.MAV_RESULT_ACCEPTED)] * 3
    msgs = box.run(20.0)
    assert count(msgs, hb) == 100            # 20 s at 5 Hz
    assert count(msgs, loop) == 4            # 20 s at one per 5 s
    assert count(msgs, store) == 0
    assert count(msgs, R.MAVLINK_MSG_ID_SYS_STATUS) == 20  # untouched: its own 1 Hz
    for mid in (hb, loop, store):
        box.command(R.MAV_CMD_GET_MESSAGE_INTERVAL, mid)
    got = of(box.run(0.3), "MESSAGE_INTERVAL")
    assert [(m.message_id, m.interval_us) for m in got] == [(hb, 200000), (loop, 5000000), (store, -1)]
    # a requested message goes out even when its stream is off
    box.command(R.MAV_CMD_REQUEST_MESSAGE, store)
    assert count(box.run(0.2), store) == 1
    # back to their own rate
    for mid in (hb, loop, store):
        box.command(R.MAV_CMD_SET_MESSAGE_INTERVAL, mid, 0)
    box.run(1.0)
    msgs = box.run(10.0)
    assert (count(msgs, hb), count(msgs, loop), count(msgs, store)) == (10, 10, 10)
    box.command(R.MAV_CMD_GET_MESSAGE_INTERVAL, hb)
    assert [m.interval_us for m in of(box.run(0.3), "MESSAGE_INTERVAL")] == [1000000]  # measured


def test_message_intervals_are_bounded_and_some_refused():
    box = Box()
    box.run(1.0)
    hb = R.MAVLINK_MSG_ID_HEARTBEAT
    box.command(R.MAV_CMD_SET_MESSAGE_INTERVAL, hb, 1)                           # 1 µs: taken as the minimum
    box.command(R.MAV_CMD_SET_MESSAGE_INTERVAL, hb, -1)                          # the heartbeat: never off
    box.command(R.MAV_CMD_SET_MESSAGE_INTERVAL, R.MAVLINK_MSG_ID_DEBRIS_MAG_SAMPLE, 2000000)  # TLM_SAMPLE_HZ
    box.command(R.MAV_CMD_SET_MESSAGE_INTERVAL, R.MAVLINK_MSG_ID_GPS_RAW_INT, 1000000)        # not ours
    box.command(R.MAV_CMD_SET_MESSAGE_INTERVAL, hb, -5)                          # not an interval
    assert acks(box.run(1.0)) == [(R.MAV_CMD_SET_MESSAGE_INTERVAL, r) for r in (
        R.MAV_RESULT_ACCEPTED, R.MAV_RESULT_DENIED, R.MAV_RESULT_DENIED, R.MAV_RESULT_DENIED, R.MAV_RESULT_DENIED)]
    msgs = box.run(10.0)
    assert count(msgs, hb) == round(10.0 / MIN_INTERVAL_S)  # 10 Hz at most, not the loop's every tick


# --- floods --------------------------------------------------------------------------------------------
def test_a_request_flood_is_answered_at_a_bounded_rate_and_counted():
    """No key (every request unauthenticated): 200 PINGs a tick for 5 s. The box decodes at most its
    frame budget a tick and answers at most the bucket's burst + rate × time; the rest is counted."""
    box = Box(key=None)
    box.ground = box.stranger
    box.run(0.5)
    up, sv = box.fsw.uplink, box.fsw.services
    pings = 0
    for _ in range(50):
        for i in range(200):
            box.stranger.send(mavlink.MAVLink_ping_message(i, i & 0xFF, 0, 0), box.now)
        pings += 200
        box.run(0.1)
    answered = len(of([r.msg for r in box.received], "PING"))
    assert answered <= sv.bucket.burst + sv.bucket.rate_hz * 5.0 + 1
    assert answered >= sv.bucket.rate_hz * 5.0 * 0.9  # the rate it promises is kept
    # every PING decoded (at most 16 a tick) was answered or counted over the bucket
    assert answered + up.counters.answers_limited == 50 * up.max_frames_per_tick
    assert up.counters.frames <= pings
    assert box.fsw.scheduler.stats.ticks > 0


def test_an_unsigned_request_flood_costs_a_bounded_decode_and_a_signed_command_still_gets_through():
    """Box with a key, on a radio (a byte stream): 25 unsigned PINGs and one signed command a tick (within
    the tick's CRC budget, 32 frames: beyond it a stream's rest is dropped, as before). At most
    `max_unsigned_per_tick` PINGs are decoded a tick; every signed command is obeyed and acknowledged."""
    box = Box()
    box.run(0.5)
    up = box.fsw.uplink
    for _ in range(20):
        for i in range(25):
            box.stranger.send(mavlink.MAVLink_ping_message(i, i & 0xFF, 0, 0), box.now)
        box.command(R.MAV_CMD_USER_1, 1)
        box.run(0.1)
    assert up.counters.unsigned_reads <= up.max_unsigned_per_tick * 20
    assert up.counters.unsigned_reads_dropped > 0
    assert acks(box.run(0.5)) == [] and len(box.runs) == 20  # every signed command obeyed
    assert acks([r.msg for r in box.received]).count((R.MAV_CMD_USER_1, R.MAV_RESULT_ACCEPTED)) == 20


@pytest.mark.parametrize("signed", [True, False])
def test_mavlink_ftp_is_refused_at_once_so_ground_stations_fall_back_to_the_parameter_protocol(signed):
    """MAVProxy asks for its parameters over MAVLink FTP first (OpenFileRO of @PARAM/param.pck): the box
    has no files and says so at once (NAK, ERR_UnknownCommand = 7, seq + 1, same session)."""
    box = Box()
    box.run(0.5)
    name = b"@PARAM/param.pck"
    req = struct.pack("<HBBBBBBI", 41, 3, 4, len(name), 0, 0, 0, 0) + name  # OpenFileRO (4)
    (box.ground if signed else box.stranger).send(mavlink.MAVLink_file_transfer_protocol_message(
        0, FSW_SYSID, FSW_COMPID, list(req.ljust(251, b"\0"))), box.now)
    ftp = of(box.run(0.3), "FILE_TRANSFER_PROTOCOL")
    assert len(ftp) == 1 and (ftp[0].target_system, ftp[0].target_component) == (GCS_SYSID, GCS_COMPID)
    seq, session, opcode, size, req_opcode = struct.unpack_from("<HBBBB", bytes(ftp[0].payload))
    assert (seq, session, opcode, size, req_opcode, ftp[0].payload[12]) == (42, 3, 129, 1, 4, 7)
    # a NAK from someone else is not answered
    nak = struct.pack("<HBBBBBBI", 1, 3, 129, 1, 4, 0, 0, 0) + b"\x07"
    box.ground.send(mavlink.MAVLink_file_transfer_protocol_message(
        0, FSW_SYSID, FSW_COMPID, list(nak.ljust(251, b"\0"))), box.now)
    assert of(box.run(0.3), "FILE_TRANSFER_PROTOCOL") == []
