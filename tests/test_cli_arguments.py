"""Every bad argument is a one-line error naming the option, key or file — never a traceback, never
a silent acceptance — and leaves every file as it was: ground.decode, ground.estimate, ground.inertia,
ground.command, ground.keys, fsw.main, bench.soak. (Scenario files: tests/test_scenario.py; output
paths: tests/test_output_paths.py; damaged .tlog files: tests/test_bad_input.py.)"""
import io
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hil import sitl
from fsw import flight
from fsw import main as fsw_main
from fsw.telemetry.signing import KeyFileError, load_key, write_key
from ground import command, decode, estimate, inertia, keys
from ground.recording import Recording, write_recording
from bench import soak
from support import exit_status, moment_recording
from support import good_tlog

ROOT = Path(__file__).resolve().parents[1]
#: the field-check tests' TLE (checksums right)
TLE1 = "1 25544U 98067A   26325.50000000  .00016717  00000-0  10270-3 0  9000"
TLE2 = "2 25544  51.6400 208.9163 0006317  69.9862  25.2906 15.50000000    09"


def snapshot(*paths):
    return [(p.read_bytes(), p.stat().st_mtime_ns) for p in paths]


def one_line_error(capsys, main, argv, status, *words, protected=()):
    """Run `main(argv)`: the exit status, the last stderr line holds `words`, no traceback, the
    `protected` files unchanged."""
    before = snapshot(*protected)
    assert exit_status(main, argv) == status
    err = capsys.readouterr().err
    assert "Traceback" not in err
    last = err.strip().splitlines()[-1]
    for w in words:
        assert w in last, (w, last)
    assert snapshot(*protected) == before
    return last


# --- ground.decode ---------------------------------------------------------------------------------

@pytest.fixture
def tlog_and_csv(tmp_path):
    src = tmp_path / "run.tlog"
    src.write_bytes(good_tlog())
    out = tmp_path / "run.csv"
    out.write_text("t_s,bx_uT,by_uT,bz_uT\n0,1,2,3\n")    # an earlier result, not to be overwritten
    return src, out


@pytest.mark.parametrize("option, value, words", [
    ("--count", "0", ("--count", ">= 1")),
    ("--count", "-5", ("--count", ">= 1")),
    ("--duration", "-1", ("--duration", "> 0")),
    ("--duration", "0", ("--duration", "> 0")),
    ("--duration", "nan", ("--duration", "finite")),
    ("--baud", "0", ("--baud",)),
])
def test_decode_refuses_a_count_or_duration_that_ends_before_it_starts(tlog_and_csv, capsys, option, value, words):
    src, out = tlog_and_csv
    one_line_error(capsys, decode.main, [str(src), "--quiet", "--csv", str(out), option, value], 2, *words,
                   protected=(src, out))


@pytest.mark.parametrize("method", ["smoother", "kotelnikov", "euler", "auto", "kalman-orbit"])
def test_decode_offers_no_ground_only_method(tlog_and_csv, capsys, method):
    src, out = tlog_and_csv
    one_line_error(capsys, decode.main, [str(src), "--quiet", "--rates-csv", str(out), "--method", method], 2,
                   "--method", "invalid choice", protected=(src, out))


def test_decode_offers_exactly_the_methods_the_box_sends():
    sent = decode.sent_methods()
    assert set(sent.values()) == set(flight.METHODS.values())
    assert set(sent) == set(flight.METHODS)          # the dialect's names are the flight software's
    assert set(decode.METHODS) - set(sent)           # the dialect knows more: those are not offered


# --- ground.estimate -------------------------------------------------------------------------------

@pytest.fixture
def header_only(tmp_path):
    path = tmp_path / "empty.csv"
    path.write_text("# source: nothing recorded\nt_s,bx_uT,by_uT,bz_uT\n")
    return path


@pytest.mark.parametrize("method", estimate.METHODS)
def test_estimate_on_a_recording_without_samples_is_a_one_line_error(header_only, tmp_path, capsys, method):
    out = tmp_path / "rates.csv"
    extra = ["--scenario", "isoi"] if method.startswith("kalman-") else []
    one_line_error(capsys, estimate.main, [str(header_only), "--rates", str(out), "--method", method, *extra], 1,
                   "empty.csv", "0 samples", method, protected=(header_only,))
    assert not out.exists()


def test_estimate_on_too_few_samples_after_decimation(tmp_path, capsys):
    t = np.arange(20.0)
    src = tmp_path / "short.csv"
    write_recording(src, Recording(t, np.column_stack([np.cos(t), np.sin(t), np.ones_like(t)]) * 30e-6))
    one_line_error(capsys, estimate.main, [str(src), "--rates", str(tmp_path / "r.csv"), "--method", "derivative",
                                           "--decimate-hz", "0.06"], 1, "2 samples", "derivative needs at least 3",
                   protected=(src,))


@pytest.mark.parametrize("option, value, words", [
    ("--sigma-uT", "0", ("--sigma-uT", "> 0")),
    ("--sigma-uT", "nan", ("--sigma-uT", "finite")),
    ("--decimate-hz", "0", ("--decimate-hz", "> 0")),
    ("--known-inertia", "nan,1,1", ("--known-inertia", "finite")),
    ("--known-inertia", "-1,1,1", ("--known-inertia", "positive definite")),
    ("--known-inertia", "1,1,3", ("--known-inertia", "triangle inequality")),
    ("--known-inertia", "1,0.5,0,0,1,0,0,0,1", ("--known-inertia", "symmetric")),
    ("--known-inertia", "1,2", ("--known-inertia", "3 or 9 values")),
])
def test_estimate_refuses_numbers_it_cannot_use(header_only, tmp_path, capsys, option, value, words):
    one_line_error(capsys, estimate.main, [str(header_only), "--rates", str(tmp_path / "r.csv"), "--method", "euler",
                                           f"{option}={value}"], 2, *words, protected=(header_only,))


@pytest.mark.parametrize("lines, words", [(["1", "2"], ("--tle", "line 1", "69")),
                                           ([f"{TLE1[:-1]}1", TLE2], ("--tle", "checksum")),
                                           ([TLE2, TLE1], ("--tle", "line 1", "does not start"))])
def test_estimate_refuses_two_lines_that_are_not_a_tle(header_only, tmp_path, capsys, lines, words):
    one_line_error(capsys, estimate.main, [str(header_only), "--rates", str(tmp_path / "r.csv"), "--tle", *lines,
                                           "--utc0", "2026-11-21T12:00:00"], 2, *words, protected=(header_only,))
    assert not (tmp_path / "r.csv").exists()


def test_estimate_refuses_a_utc0_that_is_not_a_time(header_only, tmp_path, capsys):
    one_line_error(capsys, estimate.main, [str(header_only), "--rates", str(tmp_path / "r.csv"), "--tle", "1", "2",
                                           "--utc0", "yesterday"], 2, "--utc0", "ISO 8601")


# --- ground.inertia --------------------------------------------------------------------------------

@pytest.fixture
def moment_csv(tmp_path):
    return moment_recording(tmp_path / "moment.csv", 40, slice(10, 20))


@pytest.mark.parametrize("option, value", [("--sigma-uT", "nan"), ("--sigma-uT", "0"), ("--guess", "inf"),
                                           ("--guess", "-100"), ("--running", "0")])
def test_inertia_refuses_numbers_it_cannot_use(moment_csv, tmp_path, capsys, option, value):
    out = tmp_path / "i.json"
    one_line_error(capsys, inertia.main, [str(moment_csv), str(out), "--quiet", option, value], 2, option,
                   protected=(moment_csv,))
    assert not out.exists()


def test_inertia_refuses_a_moment_no_body_could_show(moment_csv, tmp_path, capsys):
    text = moment_csv.read_text().replace("0.2,", "1e30,", 1)
    big = tmp_path / "big.csv"
    big.write_text(text)
    out = tmp_path / "i.json"
    one_line_error(capsys, inertia.main, [str(big), str(out), "--quiet"], 1, "big.csv", "m*_Nm", "1e+30 N·m",
                   protected=(big,))
    assert not out.exists()


# --- ground.command --------------------------------------------------------------------------------

@pytest.mark.parametrize("argv, words", [
    (["capsule", "--target", "1/999"], ("--target", "0..255")),
    (["capsule", "--target", "1"], ("--target", "SYS/COMP")),
    (["70000"], ("command number 70000", "0..65535")),
    (["capsule", "1e39"], ("parameter 1", "1e39", "MAVLink float")),
    (["capsule", "param2=-1e39"], ("parameter 2", "MAVLink float")),
    (["--get-param", "ÄBC"], ("parameter name", "ASCII")),
    (["--get-param", "A_NAME_LONGER_THAN_16"], ("parameter name", "16")),
    (["--set-param", "TLM_SAMPLE_HZ", "1e39"], ("--set-param TLM_SAMPLE_HZ", "MAVLink float")),
    (["capsule", "--timeout", "nan"], ("--timeout", "finite")),
    (["capsule", "--retries", "-1"], ("--retries",)),
])
def test_command_refuses_what_mavlink_cannot_carry(capsys, argv, words):
    quick = [] if "--timeout" in argv or "--retries" in argv else ["--timeout", "0.1", "--retries", "0"]
    one_line_error(capsys, command.main, ["udpout:127.0.0.1:9", *argv, "--wait", "0.1", *quick], 2, *words)


@pytest.mark.parametrize("url", ["udpout:127.0.0.1:99999", "udpin:0.0.0.0:99999", "tcp:127.0.0.1:65536",
                                 "udpout:127.0.0.1:abc", "udpout:nohost"])
def test_command_refuses_a_link_whose_port_does_not_exist(capsys, url):
    one_line_error(capsys, command.main, [url, "capsule", "--wait", "0.1", "--timeout", "0.1", "--retries", "0"], 2,
                   "url", url)


# --- mission keys ----------------------------------------------------------------------------------

def run_tool(*argv, timeout=30):
    return subprocess.run([sys.executable, "-m", *argv], cwd=ROOT, capture_output=True, text=True, timeout=timeout)


def test_keys_fingerprint_of_a_fifo_is_refused_not_waited_on(tmp_path):
    fifo = tmp_path / "key.fifo"
    os.mkfifo(fifo)
    r = run_tool("ground.keys", "fingerprint", str(fifo))
    assert r.returncode == 1 and "not a regular file" in r.stderr and "Traceback" not in r.stderr


def test_keys_new_over_a_fifo_is_refused_not_waited_on(tmp_path):
    fifo = tmp_path / "key.fifo"
    os.mkfifo(fifo)
    r = run_tool("ground.keys", "new", str(fifo), "--force")
    assert r.returncode == 2 and "not a regular file" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.parametrize("force", [[], ["--force"]])
def test_keys_new_never_writes_through_a_symlink(tmp_path, capsys, force):
    target = tmp_path / "precious.txt"
    target.write_text("not a key\n")
    link = tmp_path / "mission.key"
    link.symlink_to(target)
    one_line_error(capsys, keys.main, ["new", str(link), *force], 1, "symbolic link", protected=(target,))
    assert link.is_symlink()


def test_keys_force_replaces_a_regular_key_file(tmp_path, capsys):
    path = tmp_path / "mission.key"
    assert keys.main(["new", str(path)]) == 0
    old = load_key(path)
    assert keys.main(["new", str(path), "--force"]) == 0
    assert load_key(path) != old and (path.stat().st_mode & 0o777) == 0o600


def test_an_all_zero_key_is_refused_when_loaded_and_when_created(tmp_path, capsys):
    path = tmp_path / "zero.key"
    path.write_text("00" * 32 + "\n")
    path.chmod(0o600)
    with pytest.raises(KeyFileError, match="all 32 bytes of the key are 0x00"):
        load_key(path)
    with pytest.raises(KeyFileError, match="not a secret"):
        write_key(tmp_path / "new.key", bytes(32))
    assert not (tmp_path / "new.key").exists()
    one_line_error(capsys, keys.main, ["fingerprint", str(path)], 1, "zero.key", "0x00")
    one_line_error(capsys, fsw_main.main, ["--sitl", "--key", str(path), "--duration", "1", "--speed", "0", "--quiet",
                                           "--link", "udpout:127.0.0.1:9"], 2, "zero.key", "not a secret")


@pytest.mark.parametrize("mode, words", [(0o644, ("open.key", "accessible by others")), (None, ("missing.key",))])
def test_the_target_refuses_a_bad_key_before_it_opens_the_device(tmp_path, capsys, mode, words):
    path = tmp_path / ("open.key" if mode else "missing.key")
    if mode:
        path.write_text("ab" * 32 + "\n")
        path.chmod(mode)
    # the port does not exist either: the key is named, at parse time, not the port after start-up
    one_line_error(capsys, fsw_main.main, ["--mag-serial", str(tmp_path / "no-such-tty"), "--key", str(path),
                                           "--link", "udpout:127.0.0.1:9", "--quiet"], 2, "--key", *words)


@pytest.mark.parametrize("option", ["--sample-store", "--tle-file"])
def test_the_target_never_writes_over_its_serial_port(tmp_path, capsys, option):
    port = tmp_path / "tty"
    one_line_error(capsys, fsw_main.main, ["--mag-serial", str(port), option, str(port), "--quiet"], 2,
                   option, "--mag-serial")


def test_the_target_refuses_an_empty_serial_port(capsys):
    one_line_error(capsys, fsw_main.main, ["--mag-serial=", "--link", "udpout:127.0.0.1:9", "--quiet"], 2,
                   "--mag-serial", "empty")


# --- fsw.main --------------------------------------------------------------------------------------

@pytest.mark.parametrize("option, value", [
    ("--buffer-frames", "1000000000000"), ("--buffer-frames", "-1"),
    ("--max-sample-tlm-hz", "0"), ("--max-sample-tlm-hz", "nan"),
    ("--duration", "nan"), ("--duration", "inf"), ("--speed", "nan"), ("--speed", "-1"),
    ("--rate", "nan"), ("--rate", "0"), ("--rate", "2000"),
    ("--sample-rate", "0"), ("--sample-rate", "nan"), ("--sample-rate", "5000"),
    ("--sigma-uT", "nan"), ("--sigma-uT", "0"),
    ("--ident-inertia-guess", "nan"), ("--ident-inertia-guess", "0"),
    ("--seed", "-1"), ("--link", "udpout:127.0.0.1:99999"), ("--uplink", "udpin:0.0.0.0:70000"),
])
def test_fsw_main_refuses_numbers_it_cannot_use(capsys, option, value):
    with pytest.raises(SystemExit) as e:
        sitl.parse_args([option, value])
    assert e.value.code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert option in last


def test_a_loop_slower_than_the_samples_is_refused(capsys):
    one_line_error(capsys, fsw_main.main, ["--sitl", "--rate", "0.5", "--duration", "4", "--speed", "0", "--quiet",
                                           "--link", "udpout:127.0.0.1:9"], 2, "--rate 0.5 Hz",
                   "below the magnetometer's sample rate 1 Hz")
    one_line_error(capsys, fsw_main.main, ["--sitl", "--rate", "20", "--sample-rate", "50", "--duration", "1",
                                           "--speed", "0", "--quiet", "--link", "udpout:127.0.0.1:9"], 2,
                   "--rate 20 Hz", "sample rate 50 Hz")


def test_a_loop_at_the_sample_rate_is_warned_about():
    args = sitl.parse_args(["--rate", "1", "--duration", "3", "--speed", "0", "--quiet",
                                "--link", "udpout:127.0.0.1:9"])
    out = io.StringIO()
    sitl.run(args, out=out)
    assert "warning: --rate 1 Hz equals the sample rate" in out.getvalue()
    args = sitl.parse_args(["--rate", "5", "--duration", "1", "--speed", "0", "--quiet",
                                "--link", "udpout:127.0.0.1:9"])
    out = io.StringIO()
    sitl.run(args, out=out)
    assert "warning" not in out.getvalue()


def _mapped(pid: int, name: str) -> bool:
    try:
        return name in Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return False


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="needs /proc to see how far start-up got")
@pytest.mark.parametrize("phase", ["numpy", "numba", "llvmlite", "header", "loop"])
def test_ctrl_c_at_any_moment_of_start_up_is_one_line(phase):
    """SIGINT while the modules load (numpy, numba, llvmlite mapped: after the program's first line ran),
    once the header is printed, or once the loop runs (its first status line): "interrupted" and 130,
    or (in the loop: always) the summary and 0."""
    quiet = [] if phase == "loop" else ["--quiet"]
    p = subprocess.Popen([sys.executable, "-m", "fsw.main", "--sitl", *quiet, "--speed", "0", "--duration", "600",
                          "--link", "udpout:127.0.0.1:9"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True)
    try:
        if phase == "header":
            p.stdout.readline()
        elif phase == "loop":
            for line in p.stdout:  # ends at the end of the output, should the program stop
                if line.startswith("t="):
                    break
        else:
            deadline = time.monotonic() + 60
            while not _mapped(p.pid, phase) and p.poll() is None and time.monotonic() < deadline:
                time.sleep(0.001)
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=120)
    finally:
        p.kill()
    assert "Traceback" not in err and "KeyboardInterrupt" not in err
    if phase == "loop":
        assert p.returncode == 0 and "--- summary" in out
    else:
        assert (p.returncode, err.strip()) == (130, "interrupted") or (p.returncode == 0 and "--- summary" in out)


def test_ctrl_c_during_set_up_in_process_is_one_line(monkeypatch, capsys):
    def interrupted(cfg, **kw):
        raise KeyboardInterrupt

    monkeypatch.setattr(sitl, "build", interrupted)
    assert fsw_main.main(["--sitl", "--quiet", "--link", "udpout:127.0.0.1:9"]) == 130
    assert capsys.readouterr().err.strip() == "interrupted"


# --- bench.soak --------------------------------------------------------------------------------------

def test_soak_scenario_typo_is_a_one_line_error(capsys):
    one_line_error(capsys, soak.main, ["--duration", "150", "--quiet", "--scenario", "isio"], 2, "--scenario",
                   "unknown scenario 'isio'", "isoi")


@pytest.mark.parametrize("option, value", [("--duration", "nan"), ("--duration", "60"), ("--rate", "0"),
                                           ("--seed", "-3")])
def test_soak_refuses_numbers_it_cannot_use(capsys, option, value):
    one_line_error(capsys, soak.main, ["--duration", "150", option, value, "--quiet"], 2, option)


@pytest.mark.parametrize("module", ["fsw.main", "hil.sitl", "hil.pty_link", "ground.decode", "ground.estimate",
                                    "ground.inertia", "ground.command", "ground.keys", "ground.replay",
                                    "ground.station", "bench.accuracy", "bench.inertia", "bench.deorbit", "bench.soak",
                                    "bench.calibration", "bench.station_load", "bench.campaign.__main__"])
def test_every_tool_explains_itself(module, capsys):
    """--help of every command-line tool: exit 0 and a usage line (a stray % in a help text breaks it)."""
    import importlib

    with pytest.raises(SystemExit) as e:
        importlib.import_module(module).main(["--help"])
    assert e.value.code == 0 and capsys.readouterr().out.startswith("usage:")


# --- found by the argument fuzz (tests/test_fuzz_cli.py) -------------------------------------------

@pytest.mark.parametrize("main, argv, option", [
    (soak.main, ["--quiet", "--rate=--"], "--rate"),
    (fsw_main.main, ["--sitl", "--quiet", "--rate=--", "--link", "udpout:127.0.0.1:9"], "--rate"),
    (decode.main, ["udpin:127.0.0.1:9", "--duration=--"], "--duration"),
    (command.main, ["udpout:127.0.0.1:9", "capsule", "--timeout=--"], "--timeout"),
], ids=["bench.soak", "fsw.main", "ground.decode", "ground.command"])
def test_an_option_given_the_value_dashdash_is_refused(capsys, monkeypatch, main, argv, option):
    """Python 3.11's argparse read --rate=-- as an empty list, unchecked: a TypeError traceback later
    (or a run with a rate of [])."""
    no_work(monkeypatch, "bench.soak:run", "hil.sitl:build", "ground.decode:run", "ground.command:Session")
    one_line_error(capsys, main, argv, 2, option, "'--'")


def no_work(monkeypatch, *targets):
    """Replace the heavy work of the tools with a failure: an argument that should be refused is."""
    def reached(*args, **kwargs):
        raise AssertionError("the tool went on to its work")

    for t in targets:
        module, attr = t.split(":")
        monkeypatch.setattr(__import__(module, fromlist=[attr]), attr, reached)


def test_inertia_bench_help_is_printed(capsys):
    """A '%' in a help text made --help raise ValueError (argparse formats help with %)."""
    from bench import inertia as inertia_bench
    assert exit_status(inertia_bench.main, ["--help"]) == 0
    assert "Cramér–Rao bound on the shape ratios is <= 0.5 %" in " ".join(capsys.readouterr().out.split())


@pytest.mark.parametrize("argv, words", [
    (["--scenarios", ","], ("--scenarios", "no scenario")),
    (["--fits", "bogus"], ("--fits", "full, shape")),
    (["--fits", ""], ("--fits",)),
    (["--crb", ""], ("--crb",)),
])
def test_inertia_bench_refuses_what_would_run_nothing(capsys, monkeypatch, argv, words):
    """These ran no scenario, or no fit, and exited 0 (an empty --crb was taken for none)."""
    from bench import inertia as inertia_bench
    no_work(monkeypatch, "bench.inertia:bench_scenario", "bench.inertia:truth_record",
            "bench.inertia:crb_table")
    one_line_error(capsys, inertia_bench.main, argv, 2, *words)


@pytest.mark.parametrize("what", ["missing", "empty", "file", "not a recording", "no reference"])
def test_accuracy_on_real_recordings_refuses_a_folder_it_cannot_use(tmp_path, capsys, what):
    """--real on a missing or empty folder printed an empty table and exited 0; a CSV that is not a
    recording (or has no reference rate) raised a traceback."""
    from bench import accuracy
    folder = tmp_path / "real"
    if what != "missing":
        folder.mkdir()
    if what == "file":
        folder.rmdir()
        folder.write_text("x\n")
    elif what == "not a recording":
        (folder / "a.csv").write_text("hello\n")
    elif what == "no reference":
        t = np.arange(40.0)
        write_recording(folder / "a.csv", Recording(t, np.column_stack([np.cos(t), np.sin(t), t * 0 + 1]) * 4e-5))
    status = 1 if what in ("not a recording", "no reference") else 2
    one_line_error(capsys, accuracy.main, ["--real", str(folder)], status, str(folder))


@pytest.mark.parametrize("text", ["stall:pitch:nan", "stall:pitch:inf", "stuck:yaw:900:nan", "stall:pitch:-5"])
def test_a_fault_at_no_time_is_refused(text):
    """A fault at NaN seconds was accepted and never injected."""
    from bench.deorbit import Fault
    with pytest.raises(ValueError, match="bad fault"):
        Fault.parse(text)


@pytest.mark.parametrize("store", ["input", "folder", "key"])
def test_the_sample_store_is_checked_as_an_output(tmp_path, capsys, monkeypatch, store):
    """--sample-store was opened unchecked: naming the --replay input (or the key, or a folder) moved
    it aside to NAME.bad and wrote a store in its place."""
    src = tmp_path / "in.csv"
    t = np.arange(40.0)
    write_recording(src, Recording(t, np.column_stack([np.cos(t), np.sin(t), t * 0 + 1]) * 4e-5))
    key = tmp_path / "k.key"
    write_key(key, bytes(range(7, 39)))
    path = {"input": src, "folder": tmp_path, "key": key}[store]
    no_work(monkeypatch, "fsw.system:FlightSoftware")
    one_line_error(capsys, fsw_main.main, ["--replay", str(src), "--key", str(key), "--sample-store", str(path),
                                           "--link", "udpout:127.0.0.1:9"], 2, "--sample-store",
                   protected=(src, key))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.csv", "k.key"]


def test_command_refuses_two_things_to_do(capsys):
    """--set-param with --get-param (or a command) ran the first and ignored the rest, even invalid."""
    one_line_error(capsys, command.main, ["udpout:127.0.0.1:9", "--set-param", "TLM_SAMPLE_HZ", "5", "--get-param",
                                          "ÄBC", "--wait", "0.1"], 2, "one of COMMAND")


@pytest.mark.parametrize("main, argv, words", [
    (fsw_main.main, ["--sitl", "--key", "", "--link", "udpout:127.0.0.1:9"], ("--key", "empty path")),
    (fsw_main.main, ["--replay", "", "--link", "udpout:127.0.0.1:9"], ("INPUT.csv", "empty path")),
    (decode.main, ["udpin:127.0.0.1:9", "--key", ""], ("--key", "empty path")),
    (decode.main, [""], ("url", "empty")),
    (command.main, ["udpout:127.0.0.1:9", "capsule", "--key", ""], ("--key", "empty path")),
    (estimate.main, ["", "--rates", "r.csv"], ("input", "empty path")),
], ids=["fsw.main --key", "fsw.main --replay", "ground.decode --key", "ground.decode URL", "ground.command --key",
        "ground.estimate input"])
def test_an_empty_path_is_refused_not_taken_for_none(capsys, monkeypatch, main, argv, words):
    """An empty path (a shell variable not set) was taken for "not given": fsw.main --key "" ran with no
    key at all, --replay "" ran on target with no serial port, ground.decode "" read the current folder."""
    no_work(monkeypatch, "fsw.system:FlightSoftware", "ground.decode:run", "ground.command:Session",
            "ground.estimate:read_recording")
    one_line_error(capsys, main, argv, 2, *words)


def test_the_triangle_check_does_not_overflow_near_the_float_limit(tmp_path):
    """Principal moments near 1.8e308: their sum overflowed (a RuntimeWarning on stderr, the check on inf)."""
    import warnings

    from hil import scenario
    path = tmp_path / "big.toml"
    path.write_text((scenario.SCENARIO_DIR / "isoi.toml").read_text().replace(
        "inertia_kgm2 = [[0.058, 0.0, 0.0], [0.0, 0.058, 0.0], [0.0, 0.0, 0.011]]",
        "inertia_kgm2 = [[1e308, 0.0, 0.0], [0.0, 1e308, 0.0], [0.0, 0.0, 1e308]]"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert estimate.inertia_tensor("1e308,1e308,1e308")[0, 0] == 1e308
        assert scenario.load(str(path)).inertia_kgm2[0, 0] == 1e308
