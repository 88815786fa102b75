"""End to end on target: `fsw.main --mag-serial` against the emulated chip behind a pty receives the time
and a TLE by signed commands from `ground.command`, keeps the TLE in its file, and then accepts the
identification experiment it refused without them."""
import threading
import time
from datetime import datetime, timedelta, timezone

import numpy as np
import pytest

from fsw import main as fsw_main
from fsw.telemetry.signing import write_key
from ground import command as ground_command
from hil.mmc5983ma import EmulatedMmc5983ma
from hil.pty_link import PtyBridge
from support import circular_tle, free_udp_port

KEY = bytes(range(90, 122))


def epoch_field(dt):
    start = datetime(dt.year, 1, 1, tzinfo=timezone.utc)
    return f"{dt.year % 100:02d}{(dt - start).total_seconds() / 86400 + 1:012.8f}"


@pytest.mark.slow  # 12 s of real time on target
def test_target_takes_time_and_tle_then_runs_the_identification(tmp_path, capsys):
    key = tmp_path / "mission.key"
    write_key(key, KEY)
    tle_file = tmp_path / "tle.txt"
    l1, l2 = circular_tle(epoch=epoch_field(datetime.now(timezone.utc) - timedelta(days=2)))
    t0 = time.monotonic()
    emu = EmulatedMmc5983ma(lambda t: np.array([20e-6, -5e-6, 45e-6]), lambda: time.monotonic() - t0,
                            np.random.default_rng(5))
    up = free_udp_port()
    url = f"udpout:127.0.0.1:{up}"
    out = {}
    start = ["--key", str(key), "--retries", "10", "--timeout", "0.5", "ident_start", "source=1", "observe_free=2",
             "torque_time=2", "observe_after=2", "mx=0.1"]
    with PtyBridge(emu, rng=np.random.default_rng(6)) as bridge:
        th = threading.Thread(target=lambda: out.setdefault("status", fsw_main.main(
            ["--mag-serial", bridge.port_name, "--key", str(key), "--link", f"udpout:127.0.0.1:{free_udp_port()}",
             "--uplink", f"udpin:127.0.0.1:{up}", "--duration", "12", "--quiet", "--tle-file", str(tle_file)])))
        th.start()
        try:
            assert ground_command.main([url, *start]) == 1                        # no time, no TLE: DENIED
            assert "DENIED" in capsys.readouterr().out
            assert ground_command.main([url, "--key", str(key), "time"]) == 0
            assert ground_command.main([url, "--key", str(key), "tle", l1, l2]) == 0
            assert ground_command.main([url, *start]) == 0                        # now accepted
            text = capsys.readouterr().out
            assert "the box reports UTC" in text and "ACCEPTED" in text
        finally:
            th.join()
    assert out["status"] == 0
    assert tle_file.read_text() == f"{l1}\n{l2}\n"
    summary = capsys.readouterr().out
    assert "time and orbit: UTC" in summary and "(1 sets)" in summary and "TLE 99999" in summary
    assert ": ok;" in summary
