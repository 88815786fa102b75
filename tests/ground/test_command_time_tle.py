"""ground.command time / tle: bad TLEs are one-line usage errors before anything is sent; against the
flight software over UDP (SITL), the time and a TLE are taken, an old TLE is refused with its reason."""
import io
import threading
import time
from datetime import datetime, timedelta, timezone

import pytest

from fsw.telemetry.signing import write_key
from ground import command as ground_command
from hil import sitl
from support import circular_tle, free_udp_port

KEY = bytes(range(50, 82))


def epoch_field(dt):
    start = datetime(dt.year, 1, 1, tzinfo=timezone.utc)
    return f"{dt.year % 100:02d}{(dt - start).total_seconds() / 86400 + 1:012.8f}"


@pytest.fixture
def key_file(tmp_path):
    path = tmp_path / "mission.key"
    write_key(path, KEY)
    return str(path)


def test_epoch_field_helper():
    assert epoch_field(datetime(2026, 4, 30, 12, tzinfo=timezone.utc)) == "26120.50000000"


@pytest.mark.parametrize("args, said", [
    (["tle", "1 00005U", "2 00005"], "bad TLE (format)"),
    (["tle", *(lambda a, b: (a[:-1] + str((int(a[-1]) + 1) % 10), b))(*circular_tle())], "bad TLE (checksum)"),
    (["tle", "a", "b", "c"], "tle takes a file or the two lines"),
    (["tle", "/no/such/tle.txt"], "TLE file /no/such/tle.txt"),
    (["time", "yesterday"], "not an ISO 8601 UTC"),
    (["time", "2026-01-01T00:00:00Z", "extra"], "at most one argument"),
])
def test_bad_input_is_one_line_and_nothing_is_sent(args, said, key_file, capsys):
    port = free_udp_port()   # nobody listens: a usage error must come before any link is opened
    assert ground_command.main([f"udpout:127.0.0.1:{port}", "--key", key_file, *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and said in err[0] and "Traceback" not in err[0]


def test_a_tle_file_with_a_name_line(tmp_path):
    l1, l2 = circular_tle()
    f = tmp_path / "sat.tle"
    f.write_text(f"DEBRIS 1\n{l1}\n{l2}\n")
    assert ground_command.read_tle_args([str(f)]).line1 == l1


def test_time_and_tle_to_the_flight_software_over_udp(key_file, tmp_path, capsys):
    up_port = free_udp_port()
    args = sitl.parse_args(["--speed", "2", "--quiet", "--duration", "12", "--key", key_file,
                            "--link", f"udpout:127.0.0.1:{free_udp_port()}", "--uplink", f"udpin:127.0.0.1:{up_port}"])
    out = {}
    th = threading.Thread(target=lambda: out.setdefault("run", sitl.run(args, out=io.StringIO())))
    th.start()
    now = datetime.now(timezone.utc)
    fresh = tmp_path / "fresh.tle"
    fresh.write_text("\n".join(circular_tle(epoch=epoch_field(now - timedelta(days=1)))) + "\n")
    old = circular_tle(epoch=epoch_field(now - timedelta(days=30)))
    url = f"udpout:127.0.0.1:{up_port}"
    try:
        time.sleep(0.5)
        assert ground_command.main([url, "--key", key_file, "tle", str(fresh)]) == 1       # no time yet
        assert "set the time first" in capsys.readouterr().out
        assert ground_command.main([url, "--key", key_file, "time"]) == 0
        assert "the box reports UTC" in capsys.readouterr().out
        assert ground_command.main([url, "--key", key_file, "tle", *old]) == 1
        assert "DENIED" in (o := capsys.readouterr().out) and "older than the age limit" in o
        assert ground_command.main([url, "--key", key_file, "tle", str(fresh)]) == 0
        assert "ACCEPTED" in capsys.readouterr().out
    finally:
        th.join()
    to = out["run"].sitl.flight.timeorbit
    assert to.tle is not None and to.tle_loaded == 1 and to.tle_refused == 2 and to.clock.sets == 1
    assert abs(to.tle_age_s(out["run"].loop.t_s) - 86400.0) < 60.0   # the onboard UTC is the ground's
