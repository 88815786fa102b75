"""Command router, parameters and the uplink: what is obeyed, what is refused and counted, and the
end-to-end path from `ground.command` to the flight software over UDP."""
import io
import math
import threading
from types import SimpleNamespace

import numpy as np
import pytest

from hil import sitl
from fsw.commands import BadParam, CommandRouter, ParamTable, float_param, int_param
from fsw.flight import FlightSoftware
from fsw.telemetry.dialect import FSW_COMPID, FSW_SYSID, mavlink
from fsw.telemetry.framing import Deframer
from fsw.telemetry.signing import SigningClock, Verdict, unix_to_timestamp, write_key
from fsw.telemetry.store_forward import StoreForward
from fsw.telemetry.telemetry import Telemetry
from ground import command as ground_command
from ground.command import GroundLink, Session, parse_params, resolve_command
from hil.faults import FaultyLink
from support import SteadySource, free_udp_port

KEY = bytes(range(100, 132))
T0 = unix_to_timestamp(1_750_000_000.0)
R = mavlink


def cmd(command, *params, confirmation=0, target=(FSW_SYSID, FSW_COMPID)):
    p = list(params) + [0.0] * (7 - len(params))
    return mavlink.MAVLink_command_long_message(target[0], target[1], command, confirmation, *p)


# --- router -----------------------------------------------------------------------------------
def test_router_results_and_counters():
    r = CommandRouter()
    calls = []

    def capsule(msg, now_s):
        calls.append((int_param(msg.param1, 0, 1, "channel"), int_param(msg.param2, 0, 1, "open")))
        return R.MAV_RESULT_ACCEPTED

    def broken(msg, now_s):
        raise ZeroDivisionError("bug")

    r.register(R.MAV_CMD_DEBRIS_CAPSULE, capsule)
    r.register(R.MAV_CMD_DEBRIS_SAFE_MODE, broken)
    r.register(R.MAV_CMD_REQUEST_MESSAGE, lambda m, t: None, changes_state=False)
    assert r.handle(cmd(R.MAV_CMD_DEBRIS_CAPSULE, 1, 1), 0.0) == R.MAV_RESULT_ACCEPTED
    assert r.handle(cmd(R.MAV_CMD_DEBRIS_CAPSULE, 2, 1), 1.0) == R.MAV_RESULT_DENIED       # channel 2
    assert r.handle(cmd(R.MAV_CMD_DEBRIS_CAPSULE, 0.5, 1), 2.0) == R.MAV_RESULT_DENIED     # not an integer
    assert r.handle(cmd(R.MAV_CMD_DEBRIS_CAPSULE, math.nan, 1), 3.0) == R.MAV_RESULT_DENIED
    assert r.handle(cmd(R.MAV_CMD_DEBRIS_SAFE_MODE, 1), 4.0) == R.MAV_RESULT_FAILED         # never raises
    assert r.handle(cmd(R.MAV_CMD_DEBRIS_MAGNET_TURN, 0, 90), 5.0) == R.MAV_RESULT_UNSUPPORTED
    assert r.handle(cmd(R.MAV_CMD_DEBRIS_CAPSULE, 0, 1), 6.0, authenticated=False) == R.MAV_RESULT_DENIED
    assert r.handle(cmd(R.MAV_CMD_REQUEST_MESSAGE, 0), 7.0, authenticated=False) == R.MAV_RESULT_ACCEPTED
    assert r.handle(SimpleNamespace(command="x"), 8.0) == R.MAV_RESULT_FAILED               # not a command
    assert calls == [(1, 1)]
    c = r.counters
    assert (c.accepted, c.denied, c.failed, c.unsupported, c.unauthenticated) == (2, 3, 2, 1, 1)
    assert "bug" in c.last_error or "command" in c.last_error
    with pytest.raises(ValueError):
        r.register(R.MAV_CMD_DEBRIS_CAPSULE, capsule)
    assert r.registered() == sorted([R.MAV_CMD_DEBRIS_CAPSULE, R.MAV_CMD_DEBRIS_SAFE_MODE, R.MAV_CMD_REQUEST_MESSAGE])


def test_a_handler_says_why_in_result_param2_and_a_retry_repeats_it():
    r = CommandRouter()

    def refuse(msg, now_s):
        r.set_result_param2(7)
        return R.MAV_RESULT_DENIED

    r.register(R.MAV_CMD_DEBRIS_CAPSULE, refuse)
    r.register(R.MAV_CMD_DEBRIS_SAFE_MODE, lambda m, t: None)
    assert r.handle(cmd(R.MAV_CMD_DEBRIS_CAPSULE, 1), 0.0) == R.MAV_RESULT_DENIED and r.result_param2 == 7
    assert r.handle(cmd(R.MAV_CMD_DEBRIS_SAFE_MODE, 1), 1.0) == R.MAV_RESULT_ACCEPTED and r.result_param2 == 0
    assert r.handle(cmd(R.MAV_CMD_DEBRIS_CAPSULE, 1), 2.0) == R.MAV_RESULT_DENIED
    assert r.handle(cmd(R.MAV_CMD_DEBRIS_CAPSULE, 1, confirmation=1), 3.0) == R.MAV_RESULT_DENIED
    assert r.result_param2 == 7 and r.counters.retries == 1


def test_a_retransmission_gets_the_same_answer_without_acting_twice():
    r = CommandRouter()
    runs = []
    r.register(R.MAV_CMD_DEBRIS_MAGNET_TURN, lambda m, t: runs.append(m.param2))
    assert r.handle(cmd(R.MAV_CMD_DEBRIS_MAGNET_TURN, 0, 90), 0.0) == R.MAV_RESULT_ACCEPTED
    assert r.handle(cmd(R.MAV_CMD_DEBRIS_MAGNET_TURN, 0, 90, confirmation=1), 1.0) == R.MAV_RESULT_ACCEPTED
    assert runs == [90] and r.counters.retries == 1
    # a new command (confirmation 0), or a retry with other parameters, or too late, runs again
    assert r.handle(cmd(R.MAV_CMD_DEBRIS_MAGNET_TURN, 0, 90), 2.0) == R.MAV_RESULT_ACCEPTED
    assert r.handle(cmd(R.MAV_CMD_DEBRIS_MAGNET_TURN, 0, 45, confirmation=1), 3.0) == R.MAV_RESULT_ACCEPTED
    assert r.handle(cmd(R.MAV_CMD_DEBRIS_MAGNET_TURN, 0, 45, confirmation=2), 3.0 + 60) == R.MAV_RESULT_ACCEPTED
    assert runs == [90, 90, 45, 45]


def test_parameter_helpers():
    assert int_param(1.0, 0, 1, "x") == 1 and int_param(math.nan, 0, 1, "x", default=0) == 0
    assert float_param(-2.5, -3, 3, "x") == -2.5 and float_param(math.nan, 0, 1, "x", default=0.5) == 0.5
    for bad in (math.inf, math.nan, 1.5, 2.0):
        with pytest.raises(BadParam):
            int_param(bad, 0, 1, "x")
    with pytest.raises(BadParam):
        float_param(3.5, -3, 3, "x")
    t = ParamTable()
    box = {"v": 1.0}
    t.register("GAIN", lambda: box["v"], lambda v: box.__setitem__("v", v), 0.0, 10.0)
    t.register("MODE", lambda: 2, lambda v: None, 0, 3, integer=True)
    t.register("RO", lambda: 7, None, 0, 10)
    assert t.set("GAIN", 4.0) and box["v"] == 4.0
    assert not t.set("GAIN", 11.0) and not t.set("GAIN", math.nan) and not t.set("MODE", 1.5)
    assert not t.set("RO", 1.0) and not t.set("NOPE", 1.0) and t.rejected == 5
    assert t.names() == ["GAIN", "MODE", "RO"]


# --- the uplink inside the flight software ------------------------------------------------------
class Box:
    """Flight software on an in-memory link, a ground station at the other end."""

    def __init__(self, key=KEY, store=True):
        self.link = FaultyLink(np.random.default_rng(0), src_system=FSW_SYSID, src_component=FSW_COMPID)
        tlm = Telemetry(self.link, store=StoreForward() if store else None, key=key,
                        clock=SigningClock(epoch=T0, clock_set=True))
        self.fsw = FlightSoftware(SteadySource(), tlm, rate_hz=10, sigma_b_T=1e-7, sample_rate_hz=1.0,
                                  uplink=self.link, key=key)
        self.runs = []
        self.fsw.commands.register(R.MAV_CMD_USER_1, lambda m, t: self.runs.append(m.param1))
        self.ground = GroundLink(self.link.ground_write, KEY, SigningClock(epoch=T0, clock_set=True))
        self.deframer = Deframer()
        self.k = 0
        self.received = []

    def run(self, seconds):
        for _ in range(int(seconds * 10)):
            self.fsw.tick(self.k / 10)
            self.k += 1
            self.received += self.ground.feed(self.link.ground_read(), self.k / 10)
        return self.received

    def acks(self):
        return [(r.msg.command, r.msg.result, r.verdict) for r in self.received if r.msg.get_type() == "COMMAND_ACK"]

    def link_status(self):
        return [r.msg for r in self.received if r.msg.get_type() == "DEBRIS_LINK_STATUS"][-1]


def test_signed_commands_are_obeyed_and_everything_else_refused_and_counted():
    box = Box()
    box.run(1.0)
    box.ground.command_long(R.MAV_CMD_USER_1, [1], box.k / 10)
    box.run(0.5)
    assert box.runs == [1] and box.acks() == [(R.MAV_CMD_USER_1, R.MAV_RESULT_ACCEPTED, Verdict.OK)]
    # unsigned, signed with another key, replayed: no answer, not obeyed, counted
    GroundLink(box.link.ground_write, None).command_long(R.MAV_CMD_USER_1, [2], 0.0)
    GroundLink(box.link.ground_write, bytes(32), SigningClock(epoch=T0)).command_long(R.MAV_CMD_USER_1, [3], 0.0)
    replay = box.ground.command_long(R.MAV_CMD_USER_1, [4], box.k / 10)
    box.run(0.5)
    box.link.ground_write(replay)
    box.link.ground_write(replay)
    box.run(1.5)
    assert box.runs == [1, 4]
    c = box.fsw.uplink.counters
    assert (c.unsigned, c.bad_signature, c.replay) == (1, 1, 2)
    st = box.link_status()
    assert (st.cmd_accepted, st.rejected_unsigned, st.rejected_bad_signature, st.rejected_replay) == (2, 1, 1, 2)
    # a command for someone else is not ours to answer
    box.ground.send(cmd(R.MAV_CMD_USER_1, 5, target=(42, 1)), box.k / 10)
    box.run(0.5)
    assert box.runs == [1, 4] and box.fsw.uplink.counters.not_for_us == 1
    # telemetry is signed too: the ground verified every frame it used
    assert all(r.verdict is Verdict.OK for r in box.received)


def test_parameters_over_the_uplink():
    box = Box()
    box.ground.send(mavlink.MAVLink_param_set_message(FSW_SYSID, FSW_COMPID, b"SF_REPLAY_BPS", 1234.0,
                                                      R.MAV_PARAM_TYPE_REAL32), 0.0)
    box.run(0.5)
    values = [r.msg for r in box.received if r.msg.get_type() == "PARAM_VALUE"]
    assert values[-1].param_id == "SF_REPLAY_BPS" and values[-1].param_value == 1234.0
    assert box.fsw.tlm.store.replay_bytes_per_s == 1234.0
    # out of range: refused, the value in force is reported
    box.ground.send(mavlink.MAVLink_param_set_message(FSW_SYSID, FSW_COMPID, b"SF_REPLAY_BPS", -1.0,
                                                      R.MAV_PARAM_TYPE_REAL32), box.k / 10)
    box.ground.send(mavlink.MAVLink_param_request_list_message(FSW_SYSID, FSW_COMPID), box.k / 10)
    box.run(0.5)
    values = [r.msg for r in box.received if r.msg.get_type() == "PARAM_VALUE"]
    assert values[-4].param_id == "SF_REPLAY_BPS" and values[-4].param_value == 1234.0   # the refused set's answer
    listed = {v.param_id: v.param_value for v in values[-3:]}
    assert listed.keys() == {"TLM_SAMPLE_HZ", "RESEND_BPS", "SF_REPLAY_BPS"} and listed["SF_REPLAY_BPS"] == 1234.0
    assert box.fsw.uplink.counters.params_refused == 1


def test_without_a_key_every_state_changing_command_is_refused():
    box = Box(key=None)
    box.ground = GroundLink(box.link.ground_write, None)
    box.ground.command_long(R.MAV_CMD_USER_1, [1], 0.0)
    box.ground.send(mavlink.MAVLink_param_set_message(FSW_SYSID, FSW_COMPID, b"SF_REPLAY_BPS", 99.0,
                                                      R.MAV_PARAM_TYPE_REAL32), 0.0)
    box.ground.command_long(R.MAV_CMD_REQUEST_MESSAGE, [R.MAVLINK_MSG_ID_DEBRIS_LINK_STATUS], 0.0)
    box.run(0.5)
    assert box.runs == [] and box.fsw.tlm.store.replay_bytes_per_s != 99.0
    assert (R.MAV_CMD_USER_1, R.MAV_RESULT_DENIED, None) in box.acks()
    assert (R.MAV_CMD_REQUEST_MESSAGE, R.MAV_RESULT_ACCEPTED, None) in box.acks()   # reading is allowed
    assert box.link_status().rejected_unsigned == 1
    assert box.fsw.uplink.counters.params_refused == 1


def test_command_names_and_parameters():
    assert resolve_command("MAV_CMD_DEBRIS_CAPSULE") == resolve_command("debris_capsule") \
        == resolve_command("capsule") == resolve_command("54010") == R.MAV_CMD_DEBRIS_CAPSULE
    with pytest.raises(ground_command.UsageError):
        resolve_command("fly_to_the_moon")
    assert parse_params(R.MAV_CMD_DEBRIS_CAPSULE, ["channel=1", "open=1"])[:2] == [1.0, 1.0]
    assert parse_params(R.MAV_CMD_DEBRIS_MAGNET_TURN, ["0", "-90", "param7=nan"])[:2] == [0.0, -90.0]
    for bad in (["wings=2"], ["x"], ["1"] * 8, ["inf"]):
        with pytest.raises(ground_command.UsageError):
            parse_params(R.MAV_CMD_DEBRIS_CAPSULE, bad)
    assert "DEBRIS_CAPSULE (54010)" in ground_command.list_commands()


# --- end to end over UDP ------------------------------------------------------------------------
@pytest.fixture
def key_file(tmp_path):
    path = tmp_path / "mission.key"
    write_key(path, KEY)
    return str(path)


def start_box(argv):
    args = sitl.parse_args(["--speed", "3", "--quiet", *argv])
    out = {}
    th = threading.Thread(target=lambda: out.setdefault("run", sitl.run(args, out=io.StringIO())))
    th.start()
    return th, out


def test_ground_command_to_sitl_over_udp_on_the_telemetry_link(key_file, capsys):
    """fsw udpout → ground udpin; the ground answers to the address the telemetry comes from."""
    port = free_udp_port()
    th, out = start_box(["--duration", "6", "--key", key_file, "--link", f"udpout:127.0.0.1:{port}"])
    s = Session(f"udpin:127.0.0.1:{port}", KEY)
    try:
        assert s.find_box((FSW_SYSID, FSW_COMPID), 5.0)
        assert s.command(R.MAV_CMD_REQUEST_MESSAGE, [R.MAVLINK_MSG_ID_DEBRIS_LINK_STATUS], timeout_s=1.0) \
            == R.MAV_RESULT_ACCEPTED
        assert s.command(R.MAV_CMD_USER_2, [], timeout_s=1.0) == R.MAV_RESULT_UNSUPPORTED
        assert s.param("TLM_SAMPLE_HZ", 0.5) == 0.5
        assert s.link.verifier.counts[Verdict.OK] > 0 and s.link.rejected == 0   # telemetry verified
    finally:
        s.close()
    stranger = Session(f"udpin:127.0.0.1:{port}", None)
    try:
        assert stranger.find_box((FSW_SYSID, FSW_COMPID), 5.0)
        assert stranger.command(R.MAV_CMD_USER_2, [], timeout_s=0.5, retries=0) is None   # ignored
    finally:
        stranger.close()
    th.join()
    u = out["run"].fsw.uplink.counters
    assert u.unsigned == 1 and u.commands == 2 and u.params_set == 1


def test_ground_command_cli_with_a_separate_uplink_port(key_file, capsys):
    """fsw --uplink udpin:PORT, `python -m ground.command udpout:...:PORT`: commands while ground.decode
    keeps the telemetry port."""
    tlm_port, up_port = free_udp_port(), free_udp_port()
    th, out = start_box(["--duration", "6", "--key", key_file, "--link", f"udpout:127.0.0.1:{tlm_port}",
                         "--uplink", f"udpin:127.0.0.1:{up_port}"])
    try:
        url = f"udpout:127.0.0.1:{up_port}"
        assert ground_command.main([url, "--key", key_file, "request_message", "message_id=0"]) == 0
        assert ground_command.main([url, "--key", key_file, "USER_3", "--retries", "0"]) == 1
        assert ground_command.main([url, "--key", key_file, "--get-param", "TLM_SAMPLE_HZ"]) == 0
        assert ground_command.main([url, "USER_3", "--retries", "0", "--timeout", "0.3"]) == 3  # unsigned
        assert ground_command.main([url, "--key", key_file, "no_such_command"]) == 2
    finally:
        th.join()
    text = capsys.readouterr().out
    assert "MAV_CMD_REQUEST_MESSAGE: ACCEPTED" in text and "UNSUPPORTED" in text and "TLM_SAMPLE_HZ = 1" in text
    assert out["run"].fsw.uplink.counters.unsigned == 1
