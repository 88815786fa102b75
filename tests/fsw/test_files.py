"""fsw.files (output paths checked before any work, atomic writes) and fsw.argtypes (finite numbers in
range, link ports): the shared front door of every tool."""
import argparse
import os
import stat

import pytest

from fsw.argtypes import finite_float, int_range, link_url
from fsw.files import PathError, atomic_file, check_paths, write_atomic


@pytest.fixture
def files(tmp_path):
    src = tmp_path / "in.csv"
    src.write_text("t_s,bx_uT,by_uT,bz_uT\n")
    return tmp_path, src


def test_an_output_that_is_an_input_is_refused_by_any_name(files):
    tmp, src = files
    hard = tmp / "hard.csv"
    os.link(src, hard)
    soft = tmp / "soft.csv"
    soft.symlink_to(src)
    (tmp / "sub").mkdir()
    for same in (src, tmp / "sub" / ".." / "in.csv", hard, soft):
        with pytest.raises(PathError, match=r"--rates .* is the same file as input .*in\.csv"):
            check_paths(inputs={"input": src}, outputs={"--rates": same})


def test_two_outputs_that_are_one_file_are_refused(files):
    tmp, _ = files
    new = tmp / "new.csv"
    with pytest.raises(PathError, match="--csv .*new.csv and --rates-csv .*new.csv are the same file"):
        check_paths(outputs={"--csv": new, "--rates-csv": tmp / "." / "new.csv"})
    dangling = tmp / "link.csv"
    dangling.symlink_to(new)                           # not created yet: the same file once written
    with pytest.raises(PathError, match="are the same file"):
        check_paths(outputs={"--csv": new, "--tlog": dangling})
    assert not new.exists()


@pytest.mark.parametrize("make, message", [
    (lambda tmp: tmp / "no" / "such" / "out.csv", "directory .* does not exist"),
    (lambda tmp: tmp, "is a directory"),
    (lambda tmp: (os.mkfifo(tmp / "fifo"), tmp / "fifo")[1], "is not a regular file"),
    (lambda tmp: ((tmp / "plain").write_text("x"), tmp / "plain" / "out.csv")[1], "is not a directory"),
])
def test_an_output_that_cannot_be_written_is_refused(tmp_path, make, message):
    with pytest.raises(PathError, match=message):
        check_paths(outputs={"--csv": make(tmp_path)})


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes anywhere")
def test_an_output_in_a_read_only_directory_is_refused(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        with pytest.raises(PathError, match="not writable"):
            check_paths(outputs={"--csv": ro / "x.csv"})
    finally:
        ro.chmod(0o700)


def test_distinct_outputs_and_inputs_pass(files):
    tmp, src = files
    check_paths(inputs={"input": src, "--key": None, "--scenario": tmp / "missing.toml"},
                outputs={"--csv": tmp / "a.csv", "--rates-csv": tmp / "b.csv", "--plot": None})


def test_an_atomic_write_that_fails_leaves_the_old_file(tmp_path):
    out = tmp_path / "out.json"
    out.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_file(out) as f:
            f.write("half")
            raise RuntimeError("disk full")
    assert out.read_text() == "old" and os.listdir(tmp_path) == ["out.json"]


def test_an_atomic_write_replaces_a_symlink_never_writes_through_it(tmp_path):
    target = tmp_path / "target"
    target.write_text("keep")
    link = tmp_path / "link"
    link.symlink_to(target)
    write_atomic(link, "new\n")
    assert target.read_text() == "keep" and not link.is_symlink() and link.read_text() == "new\n"
    write_atomic(tmp_path / "key", b"secret", permissions=0o600)
    assert stat.S_IMODE((tmp_path / "key").stat().st_mode) == 0o600


@pytest.mark.parametrize("kind, text, message", [
    (finite_float(0, min_exclusive=True), "nan", "finite"),
    (finite_float(0, min_exclusive=True), "inf", "finite"),
    (finite_float(0, min_exclusive=True), "0", "must be > 0, got 0"),
    (finite_float(0, 1000), "1000.5", "must be >= 0 and <= 1000"),
    (finite_float(), "ten", "not a number"),
    (int_range(1), "0", "must be >= 1, got 0"),
    (int_range(0, 1_000_000), "1000000000000", "<= 1000000,"),
    (int_range(0), "1e12", "not a whole number"),
    (link_url, "udpout:127.0.0.1:99999", "port must be a number in 1..65535"),
    (link_url, "udpin:0.0.0.0:0", "port must be"),
    (link_url, "tcp:localhost", "expected tcp:HOST:PORT"),
])
def test_argument_types_refuse(kind, text, message):
    with pytest.raises(argparse.ArgumentTypeError, match=message):
        kind(text)


def test_argument_types_accept():
    assert finite_float(0, min_exclusive=True)("1e-3") == 1e-3
    assert int_range(0, 10)(" 7 ") == 7
    for url in ("udpin:0.0.0.0:14550", "udpout:127.0.0.1:14551", "/dev/ttyUSB0", "run.tlog", "tcp:[::1]:5760"):
        assert link_url(url) == url


def test_an_atomic_write_keeps_the_permissions_of_the_file_it_replaces(tmp_path):
    out = tmp_path / "private.csv"
    out.write_text("old")
    out.chmod(0o600)
    write_atomic(out, "new")
    assert out.read_text() == "new" and stat.S_IMODE(out.stat().st_mode) == 0o600
