"""The archive: frames in, intervals out (CSV as ground.decode writes it, a .tlog stock pymavlink reads),
a writer killed mid-ingest, a reader while it is written, bad input."""
from __future__ import annotations

import os
import sqlite3
import struct
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from fsw.telemetry.dialect import FSW_COMPID, FSW_SYSID, mavlink
from ground import decode
from ground.archive import ArchiveWriter, open_reader
from ground.archive.__main__ import main as archive_main
from ground.archive.__main__ import utc_time_us
from ground.archive.export import export_recordings
from ground.archive.store import ArchiveFeed, spans
from ground.tlog import read_tlog
from support import box_frames, exit_status, free_udp_port, pymavlink_with_debris

ROOT = Path(__file__).resolve().parents[2]
WALL0_US = 1_750_000_000_000_000       # 2025-06-15T15:06:40Z
OTHER = 7                               # a second box's system id


def tlog_bytes(frames) -> bytes:
    return b"".join(struct.pack(">Q", t) + f for t, f in frames)


@pytest.fixture(scope="module")
def two_boxes(tmp_path_factory):
    """A tlog of two boxes sending at once for 60 s, box 1 first, and the decoder's CSV/tlog/archive of it."""
    d = tmp_path_factory.mktemp("arch")
    ours = box_frames(60, wall0_us=WALL0_US)
    theirs = box_frames(60, sysid=OTHER, compid=1, wall0_us=WALL0_US + 20, run_id=0x77)
    frames = sorted(ours + theirs, key=lambda r: r[0])
    (d / "in.tlog").write_bytes(tlog_bytes(frames))
    assert decode.main([str(d / "in.tlog"), "--quiet", "--csv", str(d / "dec.csv"), "--rates-csv",
                        str(d / "dec_rates.csv"), "--archive", str(d / "a.sqlite")]) == 0
    return d, ours, frames


def without_source(path: Path) -> list[str]:
    return [line for line in path.read_text().splitlines() if not line.startswith("# source:")]


def test_the_archive_holds_every_frame_of_each_box_with_its_times(two_boxes):
    d, ours, frames = two_boxes
    conn = open_reader(d / "a.sqlite")
    rows = conn.execute("SELECT t_us, sysid, compid, msgid, box_t_us, frame FROM frames ORDER BY rowid").fetchall()
    assert [(t, f) for t, _, _, _, _, f in rows] == frames
    by_box = {(s.sysid, s.compid): s.frames for s in spans(conn)}
    assert by_box == {(FSW_SYSID, FSW_COMPID): len(ours), (OTHER, 1): len(frames) - len(ours)}
    # the box's time: the sample's time_usec (heartbeats have none)
    samples = [r for r in rows if r[3] == mavlink.MAVLINK_MSG_ID_DEBRIS_MAG_SAMPLE and r[1] == FSW_SYSID]
    assert [r[4] for r in samples] == [k * 100_000 for k in range(600)]
    assert {r[4] for r in rows if r[3] == mavlink.MAVLINK_MSG_ID_HEARTBEAT} == {None}


def test_the_csv_export_is_what_the_decoder_writes_from_the_same_frames(two_boxes):
    d, ours, _ = two_boxes
    assert archive_main(["export", "--archive", str(d / "a.sqlite"), "--box", str(FSW_SYSID),
                         "--csv", str(d / "ex.csv"), "--rates-csv", str(d / "ex_rates.csv")]) == 0
    assert without_source(d / "ex.csv") == without_source(d / "dec.csv")
    assert without_source(d / "ex_rates.csv") == without_source(d / "dec_rates.csv")
    assert len([ln for ln in without_source(d / "ex.csv") if ln[0].isdigit()]) == 600
    assert not (d / f"ex.{OTHER}-1.run1.csv").exists()          # only the box asked for


def test_frames_the_recordings_do_not_use_still_count_in_the_link_accounting(two_boxes, tmp_path):
    """The export decodes only the messages the recordings are made of; the others go to the decoder's
    link accounting undecoded: it counts the same as a decoder fed every frame (with a frame lost)."""
    d, ours, _ = two_boxes
    lossy = ours[:500] + ours[501:]                        # a status frame lost: the accounting sees the gap
    with ArchiveWriter(tmp_path / "a.sqlite") as w:
        for t_us, f in lossy:
            w.add_frame(t_us, f[5], f[6], f[7] | f[8] << 8 | f[9] << 16, None, f)
    out = export_recordings(open_reader(tmp_path / "a.sqlite"), FSW_SYSID, tmp_path / "ex.csv")
    (tmp_path / "in.tlog").write_bytes(tlog_bytes(lossy))
    whole = decode.run(str(tmp_path / "in.tlog"), quiet=True)
    src = (FSW_SYSID, FSW_COMPID)
    assert out.decoder.stats.sources[src].as_dict() == whole.stats.sources[src].as_dict()
    assert out.decoder.stats.sources[src].lost == 1
    assert sum(out.decoder.frames_by_type.values()) < len(lossy)     # not every frame was decoded


def test_an_interval_export_is_the_decoding_of_that_interval_alone(two_boxes, tmp_path):
    d, ours, _ = two_boxes
    lo, hi = WALL0_US + 10_000_000, WALL0_US + 25_000_000
    part = [r for r in ours if lo <= r[0] < hi]
    (tmp_path / "part.tlog").write_bytes(tlog_bytes(part))
    assert decode.main([str(tmp_path / "part.tlog"), "--quiet", "--csv", str(tmp_path / "dec.csv")]) == 0
    assert archive_main(["export", "--archive", str(d / "a.sqlite"), "--box", "1", "--from",
                         "2025-06-15T15:06:50Z", "--to", str((hi) / 1e6), "--csv", str(tmp_path / "ex.csv"),
                         "--tlog", str(tmp_path / "ex.tlog")]) == 0
    assert without_source(tmp_path / "ex.csv") == without_source(tmp_path / "dec.csv")
    assert (tmp_path / "ex.tlog").read_bytes() == (tmp_path / "part.tlog").read_bytes()   # exact frames
    assert len([ln for ln in without_source(tmp_path / "ex.csv") if ln[0].isdigit()]) == 150


def test_the_tlog_export_reads_back_with_the_project_decoder_and_stock_mavlogdump(two_boxes, tmp_path):
    d, ours, _ = two_boxes
    out = tmp_path / "box1.tlog"
    assert archive_main(["export", "--archive", str(d / "a.sqlite"), "--box", "1", "--tlog", str(out)]) == 0
    assert out.read_bytes() == tlog_bytes(ours)
    reader = read_tlog(out)
    msgs = [m for r in reader for m in r.messages]
    assert len(msgs) == len(ours) and not reader.report.damaged
    assert {m.get_type() for m in msgs} == {"HEARTBEAT", "DEBRIS_MAG_SAMPLE", "DEBRIS_RATE_ESTIMATE",
                                            "DEBRIS_SIM_STATE", "SYS_STATUS", "DEBRIS_MAG_STATUS",
                                            "ATTITUDE_QUATERNION"}
    mavlogdump = Path(sys.executable).with_name("mavlogdump.py")
    if not mavlogdump.exists():
        pytest.skip("pymavlink's mavlogdump.py is not installed beside the interpreter")
    # the stock tool as a user runs it, the project's bindings installed as pymavlink's dialect "debris"
    # (docs/ground.md), on an export made by the command line
    exported = tmp_path / "cli.tlog"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(pymavlink_with_debris(tmp_path / "py")), str(ROOT)]))
    made = subprocess.run([sys.executable, "-m", "ground.archive", "export", "--archive", str(d / "a.sqlite"),
                           "--box", "1", "--tlog", str(exported)], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=300)
    assert made.returncode == 0, made.stderr
    assert exported.read_bytes() == out.read_bytes()
    res = subprocess.run([sys.executable, str(mavlogdump), "--dialect", "debris", "--types", "DEBRIS_MAG_SAMPLE",
                          str(exported)], capture_output=True, text=True, timeout=300, env=env, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    lines = [ln for ln in res.stdout.splitlines() if "DEBRIS_MAG_SAMPLE" in ln]
    assert len(lines) == 600 and "seq : 599" in lines[-1]
    assert "seq : 0," in lines[0] and "run_id : 4660" in lines[0]


WRITER = textwrap.dedent("""
    import sys
    import time
    from ground.archive import ArchiveWriter
    path, period, max_pending, n = sys.argv[1], float(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
    frame = bytes(range(40))
    now = [0.0]
    with ArchiveWriter(path, commit_period_s=period, max_pending=max_pending, clock=lambda: now[0]) as w:
        for k in range(n):
            t_us = 1_750_000_000_000_000 + k * 1000          # a frame every millisecond (the writer's clock)
            now[0] = k * 1e-3
            w.add_frame(t_us, 1, 191, 54000, k, frame)
            if k % 100 == 99:
                print(t_us, flush=True)
                time.sleep(0.001)                             # let a reader in between the commits
    """)


def start_writer(path, period, max_pending, n):
    return subprocess.Popen([sys.executable, "-c", WRITER, str(path), str(period), str(max_pending), str(n)],
                            cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)), stdout=subprocess.PIPE, text=True)


def test_a_writer_killed_mid_ingest_loses_at_most_the_last_second(tmp_path):
    path = tmp_path / "a.sqlite"
    proc = start_writer(path, 0.5, 20_000, 10**7)
    try:
        for line in proc.stdout:
            announced = int(line)
            if announced >= 1_750_000_000_000_000 + 20_000_000:      # 20 s of receive time in
                break
        proc.kill()
        proc.wait(timeout=60)
    finally:
        proc.kill()
    conn = open_reader(path)
    assert conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    n, last, total = conn.execute("SELECT count(*), max(t_us), sum(box_t_us) FROM frames").fetchone()
    assert last >= announced - 1_000_000                       # what was handed over a second before: kept
    assert n == (last - 1_750_000_000_000_000) // 1000 + 1      # whole, in order, no gap
    assert total == n * (n - 1) // 2


def test_a_reader_sees_whole_transactions_while_the_archive_is_written(tmp_path):
    path = tmp_path / "a.sqlite"
    batch, n = 500, 40_000
    ArchiveWriter(path).close()                                   # the file exists before the reader opens it
    proc = start_writer(path, 1e9, batch, n)
    seen = []
    try:
        conn = open_reader(path)
        while True:
            count, top = conn.execute("SELECT count(*), max(box_t_us) FROM frames").fetchone()
            seen.append(count)
            assert count % batch == 0 and (count == 0 or top == count - 1)
            if proc.poll() is not None and count == n:
                break
            assert proc.poll() is None or proc.returncode == 0
    finally:
        proc.kill()
        proc.wait(timeout=60)
    assert seen == sorted(seen) and seen[-1] == n
    assert len(set(seen)) > 2                                    # it did read while the writer wrote


def test_a_tlog_decoded_to_a_tlog_keeps_its_time_stamps(tmp_path):
    """Time stamps are rounded to the µs, not truncated: t × 1e-6 × 1e6 is below t for many t (for 8 % of
    these), and the record went 4 µs back (the link-id bits cleared)."""
    frames = box_frames(30)
    assert any(int(t * 1e-6 * 1e6) != t for t, _ in frames)
    (tmp_path / "in.tlog").write_bytes(tlog_bytes(frames))
    decode.run(str(tmp_path / "in.tlog"), tlog=tmp_path / "out.tlog", quiet=True, archive=tmp_path / "a.sqlite")
    assert (tmp_path / "out.tlog").read_bytes() == (tmp_path / "in.tlog").read_bytes()
    assert archive_main(["export", "--archive", str(tmp_path / "a.sqlite"), "--box", "1", "--tlog",
                         str(tmp_path / "ex.tlog")]) == 0
    assert (tmp_path / "ex.tlog").read_bytes() == (tmp_path / "in.tlog").read_bytes()
    assert (tmp_path / "a.sqlite").stat().st_mode & 0o777 == 0o666 & ~_umask()


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def test_list_shows_each_box_and_its_stretches(two_boxes, capsys):
    d, ours, frames = two_boxes
    assert archive_main(["list", "--archive", str(d / "a.sqlite")]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out == [f"box 1/{FSW_COMPID}: 2025-06-15T15:06:40.000Z to 2025-06-15T15:07:39.900Z  (59.9 s, "
                   f"{len(ours)} frames)",
                   f"box {OTHER}/1: 2025-06-15T15:06:40.000Z to 2025-06-15T15:07:39.900Z  (59.9 s, "
                   f"{len(frames) - len(ours)} frames)"]


def test_times_are_iso_utc_or_unix_seconds():
    assert utc_time_us("2025-06-15T15:06:40Z") == WALL0_US
    assert utc_time_us("2025-06-15 15:06:40") == WALL0_US
    assert utc_time_us("2025-06-15T17:06:40+02:00") == WALL0_US
    assert utc_time_us("1750000000.5") == WALL0_US + 500_000
    for bad in ("yesterday", "nan", "inf", ""):
        with pytest.raises(ValueError):
            utc_time_us(bad)


@pytest.mark.parametrize("args, says", [
    (["export", "--box", "1", "--csv", "{d}/x.csv", "--archive", "{d}/none.sqlite"], "no such archive"),
    (["export", "--box", "1", "--archive", "{d}/a.sqlite"], "give --csv"),
    (["export", "--box", "1", "--tlog", "{d}/a.sqlite", "--archive", "{d}/a.sqlite"], "overwrite an input"),
    (["export", "--box", "1", "--csv", "{d}/x.csv", "--from", "soon", "--archive", "{d}/a.sqlite"], "not a time"),
    (["export", "--box", "1", "--csv", "{d}/x.csv", "--from", "20", "--to", "10", "--archive", "{d}/a.sqlite"],
     "after --from"),
    (["export", "--box", "0", "--csv", "{d}/x.csv", "--archive", "{d}/a.sqlite"], "--box"),
    (["list", "--archive", "{d}/in.tlog"], "not an archive"),
    (["list", "--archive", "{d}/other.sqlite"], "not an archive"),
])
def test_bad_input_is_one_line_and_exit_status_2(two_boxes, args, says, capsys):
    d = two_boxes[0]
    sqlite3.connect(d / "other.sqlite").execute("CREATE TABLE IF NOT EXISTS t (x)").connection.close()
    assert exit_status(archive_main, [a.format(d=d) for a in args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert says in err[-1] and "Traceback" not in "\n".join(err)


def test_an_empty_interval_writes_nothing(two_boxes, tmp_path, capsys):
    d = two_boxes[0]
    assert archive_main(["export", "--archive", str(d / "a.sqlite"), "--box", "3", "--csv", str(tmp_path / "x.csv"),
                         "--tlog", str(tmp_path / "x.tlog")]) == 1
    assert "no frames of box 3" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_a_live_decoder_archives_by_default_and_not_when_told(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    from ground.archive import default_path

    assert default_path() == tmp_path / "data" / "debris-box" / "archive.sqlite"
    # a .tlog is not archived unless asked (it is a record already)
    (tmp_path / "in.tlog").write_bytes(tlog_bytes(box_frames(2)))
    assert decode.main([str(tmp_path / "in.tlog"), "--quiet"]) == 0
    assert not default_path().exists()
    # a live link is, in the default place (nothing arrives here: the archive is made, empty)
    url = f"udpin:127.0.0.1:{free_udp_port()}"
    assert decode.main([url, "--quiet", "--duration", "0.3", "--no-archive"]) == 1
    assert not default_path().exists()
    assert decode.main([url, "--quiet", "--duration", "0.3"]) == 1
    assert open_reader(default_path()).execute("SELECT count(*) FROM frames").fetchone()[0] == 0


def test_a_live_decoder_killed_leaves_an_archive_that_holds_what_a_reader_saw(tmp_path):
    """ground.decode on UDP, archiving by default; a second reader polls the archive while the frames
    arrive; after a kill -9 the file opens, checks, and holds a prefix of what was sent, at least as much
    as the reader saw."""
    import signal
    import socket
    import time

    from support import wait_udp_bound

    port = free_udp_port()
    env = dict(os.environ, PYTHONPATH=str(ROOT), XDG_DATA_HOME=str(tmp_path / "data"))
    archive = tmp_path / "data" / "debris-box" / "archive.sqlite"
    proc = subprocess.Popen([sys.executable, "-m", "ground.decode", f"udpin:127.0.0.1:{port}", "--quiet",
                             "--no-resend"], cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    sent = [f for _, f in box_frames(120)]
    seen = []
    try:
        wait_udp_bound(port)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            deadline = time.monotonic() + 120
            for i, frame in enumerate(sent):
                sock.sendto(frame, ("127.0.0.1", port))
                time.sleep(0.002)
                if i % 20 == 0 and archive.exists():
                    conn = open_reader(archive)
                    seen.append(conn.execute("SELECT count(*) FROM frames").fetchone()[0])
                    conn.close()
                    if seen[-1] >= 300:
                        break
                assert time.monotonic() < deadline, "the decoder never archived"
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=60)
    finally:
        proc.kill()
        proc.communicate(timeout=60)
    assert seen == sorted(seen) and seen[-1] >= 300
    conn = open_reader(archive)
    assert conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    kept = [f for (f,) in conn.execute("SELECT frame FROM frames ORDER BY rowid")]
    assert len(kept) >= seen[-1] and kept == sent[:len(kept)]


def test_a_default_archive_that_cannot_be_made_is_a_usage_error(tmp_path, monkeypatch, capsys):
    (tmp_path / "file").write_text("not a directory")
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "file"))
    assert exit_status(decode.main, [f"udpin:127.0.0.1:{free_udp_port()}", "--duration", "0.1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "--no-archive" in err[-1] and "Traceback" not in "\n".join(err)


def test_the_rates_of_another_method_are_what_the_decoder_writes_for_it(two_boxes, tmp_path):
    d = two_boxes[0]
    assert decode.main([str(d / "in.tlog"), "--quiet", "--method", "derivative", "--rates-csv",
                        str(tmp_path / "dec.csv")]) == 0
    assert archive_main(["export", "--archive", str(d / "a.sqlite"), "--box", "1", "--method", "derivative",
                         "--rates-csv", str(tmp_path / "ex.csv")]) == 0
    assert without_source(tmp_path / "ex.csv") == without_source(tmp_path / "dec.csv")
    assert "derivative" in (tmp_path / "ex.csv").read_text()


class _FillingUp(ArchiveFeed):
    """The archive's disk fills up after its first commit (SQLite's own limit on the file's pages)."""

    def __init__(self, path, say):
        super().__init__(path, say)
        pages = self.writer.conn.execute("PRAGMA page_count").fetchone()[0]
        self.writer.conn.execute(f"PRAGMA max_page_count = {pages + 1}")


def test_an_archive_that_fails_mid_run_is_said_once_and_the_recording_is_still_written(tmp_path, monkeypatch):
    frames = box_frames(60, wall0_us=WALL0_US)
    (tmp_path / "in.tlog").write_bytes(tlog_bytes(frames))
    assert decode.main([str(tmp_path / "in.tlog"), "--quiet", "--csv", str(tmp_path / "whole.csv")]) == 0
    monkeypatch.setattr(decode, "ArchiveFeed", _FillingUp)
    lines = []
    dec = decode.run(str(tmp_path / "in.tlog"), csv=tmp_path / "dec.csv", archive=tmp_path / "a.sqlite",
                     on_line=lines.append)
    failed = [line for line in lines if line.startswith("archive failed")]
    assert len(failed) == 1 and "full" in failed[0]
    assert dec.archive_error is not None and dec.archive_lost > 0
    assert dec.archived + dec.archive_lost == dec.frames == len(frames)
    assert without_source(tmp_path / "dec.csv") == without_source(tmp_path / "whole.csv")
    with sqlite3.connect(tmp_path / "a.sqlite") as conn:
        assert conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        assert conn.execute("SELECT count(*) FROM frames").fetchone()[0] == dec.archived
