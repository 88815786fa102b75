"""No tool overwrites its input, nor one output with another, by any name (the same path, a hard
link, a symbolic link), and every output path is checked before any work: exit status 2, one line
naming both paths, the input untouched (bytes and modification time)."""
import os

import pytest

from fsw import main as fsw_main
from ground import decode, estimate, inertia
from bench import deorbit, soak
from support import exit_status, free_udp_port, moment_recording
from support import good_tlog


def snapshot(path):
    return path.read_bytes(), path.stat().st_mtime_ns


@pytest.fixture
def tlog(tmp_path):
    path = tmp_path / "run.tlog"
    path.write_bytes(good_tlog())
    return path


@pytest.fixture
def csv(tmp_path):
    return moment_recording(tmp_path / "run.csv", 30, slice(10, 15))


def refused(capsys, main, argv, *protected, message="is the same file as"):
    before = [snapshot(p) for p in protected]
    assert exit_status(main, argv) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert err.strip().splitlines()[-1].startswith("python -m")      # argparse's one error line
    assert [snapshot(p) for p in protected] == before
    return err


def test_decode_refuses_its_tlog_as_csv(tlog, capsys):
    refused(capsys, decode.main, [str(tlog), "--quiet", "--csv", str(tlog)], tlog)


def test_decode_refuses_its_tlog_through_a_hard_or_symbolic_link(tlog, tmp_path, capsys):
    hard, soft = tmp_path / "hard.csv", tmp_path / "soft.csv"
    os.link(tlog, hard)
    soft.symlink_to(tlog)
    for other in (hard, soft):
        refused(capsys, decode.main, [str(tlog), "--quiet", "--rates-csv", str(other)], tlog)


@pytest.mark.parametrize("first, second", [("--csv", "--tlog"), ("--csv", "--rates-csv"), ("--rates-csv", "--tlog")])
def test_decode_refuses_two_outputs_in_one_file(tlog, tmp_path, capsys, first, second):
    out = tmp_path / "out.csv"
    out.write_text("keep me\n")
    err = refused(capsys, decode.main, [str(tlog), "--quiet", first, str(out), second, str(out)], tlog, out,
                  message="are the same file")
    assert first in err and second in err


def test_decode_checks_the_csv_path_before_listening(tmp_path, capsys):
    """The CSV used to fail only when the live session ended; now before the link is opened."""
    port = free_udp_port()
    err = refused(capsys, decode.main, [f"udpin:127.0.0.1:{port}", "--quiet", "--duration", "2",
                                        "--csv", str(tmp_path / "missing" / "run.csv")],
                  message="does not exist")
    assert "--csv" in err


def test_estimate_refuses_its_input_as_rates(csv, capsys):
    refused(capsys, estimate.main, [str(csv), "--rates", str(csv), "--method", "boer"], csv)


def test_estimate_refuses_the_plot_over_the_rates(csv, tmp_path, capsys):
    out = tmp_path / "r.csv"
    refused(capsys, estimate.main, [str(csv), "--rates", str(out), "--method", "boer", "--plot", str(out)], csv,
            message="are the same file")
    assert not out.exists()


@pytest.mark.parametrize("plot, message", [("missing/rates.png", "does not exist"),
                                           ("rates.txt", "cannot write a plot")])
def test_estimate_checks_the_plot_before_the_fit(csv, tmp_path, capsys, plot, message):
    out = tmp_path / "r.csv"
    refused(capsys, estimate.main, [str(csv), "--rates", str(out), "--method", "smoother", "--plot",
                                    str(tmp_path / plot)], csv, message=message)
    assert not out.exists()


def test_inertia_refuses_its_input_as_output(csv, capsys):
    refused(capsys, inertia.main, [str(csv), str(csv), "--quiet"], csv)
    refused(capsys, estimate.main, [str(csv), "--inertia", str(csv)], csv)


@pytest.mark.parametrize("plot, message", [("missing/running.png", "does not exist"),
                                           ("out.json", "are the same file"), ("running.jpgg", "cannot write a plot")])
def test_inertia_checks_the_plot_before_the_fit(csv, tmp_path, capsys, plot, message):
    out = tmp_path / "out.json"
    refused(capsys, inertia.main, [str(csv), str(out), "--quiet", "--plot", str(tmp_path / plot)], csv,
            message=message)
    assert not out.exists()


def test_replay_refuses_its_recording_as_rates_out(csv, capsys):
    refused(capsys, fsw_main.main, ["--replay", str(csv), "--rates-out", str(csv), "--quiet",
                                    "--link", "udpout:127.0.0.1:9"], csv)


def test_replay_refuses_the_key_as_rates_out(csv, tmp_path, capsys):
    key = tmp_path / "mission.key"
    key.write_text(bytes(range(32)).hex() + "\n")
    key.chmod(0o600)
    refused(capsys, fsw_main.main, ["--replay", str(csv), "--rates-out", str(key), "--key", str(key), "--quiet",
                                    "--link", "udpout:127.0.0.1:9"], csv, key)


def test_soak_checks_its_json_path_at_start(tmp_path, capsys):
    refused(capsys, soak.main, ["--duration", "150", "--quiet", "--json", str(tmp_path / "no" / "soak.json")],
            message="does not exist")


def test_deorbit_bench_refuses_one_file_for_json_and_plot(tmp_path, capsys):
    out = tmp_path / "bench.png"
    refused(capsys, deorbit.main, ["--duration", "10", "--json", str(out), "--plot", str(out)],
            message="are the same file")
    assert not out.exists()
