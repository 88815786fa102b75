"""What survives a restart (fsw.persist): a command accepted before a restart is refused when replayed
after it, the signing clock never goes back, the time comes back on the same boot only, a torn file is
never loaded."""
import json
import time

from fsw.persist import BoxState
from fsw.telemetry.dialect import mavlink
from fsw.telemetry.signing import SigningClock, Verdict, Verifier
from fsw.timeorbit import TimeOrbit
from ground.command import GroundLink

KEY = bytes(range(40, 72))


class Mono:
    def __init__(self, t=1000.0):
        self.t = t

    def __call__(self):
        return self.t


def box_verifier():
    return Verifier(KEY, SigningClock(clock_set=True, unix_time=time.time))


def signed_command():
    sent = []
    ground = GroundLink(sent.append, key=KEY, clock=SigningClock(clock_set=True, unix_time=time.time))
    ground.command_long(mavlink.MAV_CMD_REQUEST_MESSAGE, [1], 0.0)
    return sent[0]


def run(state, verifier, frame, now_s=1.0):
    """The box before its restart: its state restored (none yet), a frame taken, the loop's tick, exit."""
    state.restore(verifier, None)
    verdict = verifier.check(frame, now_s)
    state.tick(now_s)
    state.close()
    return verdict


def test_a_replayed_command_stays_refused_across_a_restart(tmp_path):
    frame = signed_command()
    first = box_verifier()
    assert run(BoxState(tmp_path, monotonic=Mono(), boot_id="a"), first, frame) is Verdict.OK
    # the same frame to a box that kept nothing: accepted again (the replay this closes)
    assert box_verifier().check(frame, 0.0) is Verdict.OK
    restarted = box_verifier()
    state = BoxState(tmp_path, monotonic=Mono(), boot_id="a")
    state.restore(restarted, None)
    assert state.notes == ["signing state: 1 command streams restored (a replayed command stays refused)"]
    assert restarted.check(frame, 0.0) is Verdict.REPLAY
    assert restarted.clock.last >= first.clock.last
    assert restarted.check(signed_command(), 0.0) is Verdict.OK  # a new command is taken
    state.close()


def test_a_torn_signing_file_is_not_loaded(tmp_path):
    run(BoxState(tmp_path, monotonic=Mono(), boot_id="a"), box_verifier(), signed_command())
    path = tmp_path / "signing.json"
    path.write_bytes(path.read_bytes()[:-30])
    v = box_verifier()
    state = BoxState(tmp_path, monotonic=Mono(), boot_id="a")
    state.restore(v, None)
    assert v.streams == {} and "torn" in state.notes[0]
    state.close()


def test_the_signing_clock_is_saved_every_minute_without_commands(tmp_path):
    v = box_verifier()
    state = BoxState(tmp_path, monotonic=Mono(), boot_id="a")
    state.restore(v, None)
    state.tick(0.0)
    v.clock.now(0.0)
    state.tick(61.0)
    state.close()
    saved = json.loads((tmp_path / "signing.json").read_text())["payload"]
    assert saved["clock_last"] == v.clock.last and saved["streams"] == []


def test_the_time_comes_back_after_a_restart_on_the_same_boot_only(tmp_path):
    mono = Mono(1000.0)
    to = TimeOrbit()
    state = BoxState(tmp_path, monotonic=mono, boot_id="boot-1")
    state.restore(None, to)
    to.set_time(5.0, 1.8e9)           # the ground sets the time at loop time 5 s
    state.tick(5.0)
    state.close()
    mono.t = 1100.0                   # the service restarts 100 s later, loop time from 0 again
    to2 = TimeOrbit()
    state = BoxState(tmp_path, monotonic=mono, boot_id="boot-1")
    state.restore(None, to2)
    assert "same boot" in state.notes[0] and not to2.clock.known
    state.tick(0.0)
    assert abs(to2.utc_s(0.0) - (1.8e9 + 100.0)) < 1e-6
    state.close()
    to3 = TimeOrbit()
    state = BoxState(tmp_path, monotonic=Mono(5.0), boot_id="boot-2")  # after a reboot
    state.restore(None, to3)
    state.tick(0.0)
    assert "reboot" in state.notes[0] and not to3.clock.known
    state.close()


def test_save_errors_are_counted(tmp_path):
    state = BoxState(tmp_path / "missing", monotonic=Mono(), boot_id="a")
    assert run(state, box_verifier(), signed_command()) is Verdict.OK
    assert state.save_errors == 1 and state.saves == 0 and "signing" in state.summary_line()
