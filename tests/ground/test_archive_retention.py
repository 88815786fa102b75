"""`python -m ground.archive prune`: a box's frames before a time leave the archive only kept in a .tlog or
explicitly discarded, it says what it deleted, and the rest of the archive (other boxes, later frames,
frames arriving meanwhile) stays."""
from __future__ import annotations

import struct

import pytest

from ground.archive import ArchiveWriter, open_reader
from ground.archive.__main__ import main as archive_main
from ground.archive.retention import prune
from support import box_frames, exit_status

WALL0_US = 1_750_000_000_000_000       # 2025-06-15T15:06:40Z
CUT_US = WALL0_US + 20_000_000         # 20 s in
OTHER = 7


def tlog_bytes(frames) -> bytes:
    return b"".join(struct.pack(">Q", t) + f for t, f in frames)


@pytest.fixture
def archive(tmp_path):
    ours = box_frames(60, wall0_us=WALL0_US)
    theirs = box_frames(60, sysid=OTHER, compid=1, wall0_us=WALL0_US + 20, run_id=0x77)
    path = tmp_path / "a.sqlite"
    with ArchiveWriter(path) as w:
        for t_us, f in sorted(ours + theirs, key=lambda r: r[0]):
            w.add_frame(t_us, f[5], f[6], f[7] | f[8] << 8 | f[9] << 16, None, f)
    return path, ours, theirs


def rows(path, sysid):
    conn = open_reader(path)
    try:
        return conn.execute("SELECT t_us, frame FROM frames WHERE sysid = ? ORDER BY rowid", (sysid,)).fetchall()
    finally:
        conn.close()


def test_prune_keeps_the_frames_in_a_tlog_first_and_says_what_it_deleted(archive, tmp_path, capsys):
    path, ours, theirs = archive
    early = [r for r in ours if r[0] < CUT_US]
    assert archive_main(["prune", "--archive", str(path), "--box", "1", "--before", "2025-06-15T15:07:00Z",
                         "--tlog", str(tmp_path / "old.tlog")]) == 0
    said = capsys.readouterr().out.strip()
    assert said == (f"deleted {len(early)} frames of box 1 received 2025-06-15T15:06:40.000Z to "
                    f"2025-06-15T15:06:59.900Z: kept in {tmp_path / 'old.tlog'}")
    assert (tmp_path / "old.tlog").read_bytes() == tlog_bytes(early)          # every frame deleted, exactly
    assert rows(path, 1) == [r for r in ours if r[0] >= CUT_US]                 # the rest of the box stays
    assert rows(path, OTHER) == theirs                                          # other boxes untouched
    assert open_reader(path).execute("PRAGMA integrity_check").fetchone()[0] == "ok"


def test_prune_without_a_copy_must_be_asked_for(archive, tmp_path, capsys):
    path, ours, _ = archive
    assert exit_status(archive_main, ["prune", "--archive", str(path), "--box", "1", "--before",
                                      str(CUT_US / 1e6)]) == 2
    assert "--discard" in capsys.readouterr().err.strip().splitlines()[-1]
    assert rows(path, 1) == ours                                                # nothing deleted
    assert archive_main(["prune", "--archive", str(path), "--box", "1", "--before", str(CUT_US / 1e6),
                         "--discard"]) == 0
    assert "discarded, no copy kept" in capsys.readouterr().out
    assert rows(path, 1) == [r for r in ours if r[0] >= CUT_US]


def test_nothing_before_the_time_deletes_nothing_and_writes_no_copy(archive, tmp_path, capsys):
    path, ours, _ = archive
    assert archive_main(["prune", "--archive", str(path), "--box", "1", "--before", str(WALL0_US / 1e6),
                         "--tlog", str(tmp_path / "old.tlog")]) == 0
    assert "nothing deleted" in capsys.readouterr().out
    assert not (tmp_path / "old.tlog").exists() and rows(path, 1) == ours


@pytest.mark.parametrize("args, says", [
    (["--tlog", "{a}"], "overwrite an input"),
    (["--tlog", "{d}/x.tlog", "--discard"], "not allowed with"),
    (["--discard", "--before", "soon"], "not a time"),
])
def test_bad_prune_input_is_one_line_and_exit_status_2(archive, args, says, capsys):
    path, ours, _ = archive
    argv = ["prune", "--archive", str(path), "--box", "1"] + (["--before", "1750000010"] if "--before" not in args
                                                              else [])
    assert exit_status(archive_main, argv + [a.format(a=path, d=path.parent) for a in args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert says in err[-1] and "Traceback" not in "\n".join(err)
    assert rows(path, 1) == ours


def test_frames_arriving_while_the_copy_is_written_stay(archive, tmp_path, monkeypatch):
    """A station writes frames received before the time (a .tlog imported meanwhile) while the copy is made:
    they were not in the copy, so they are not deleted."""
    from ground.archive import retention

    path, ours, _ = archive
    late = box_frames(1, wall0_us=WALL0_US + 5_000_000, run_id=0x99)[:3]
    real = retention.export_tlog

    def export_then_a_station_writes(*a, **k):
        out = real(*a, **k)
        with ArchiveWriter(path) as w:
            for t_us, f in late:
                w.add_frame(t_us, f[5], f[6], f[7] | f[8] << 8 | f[9] << 16, None, f)
        return out

    monkeypatch.setattr(retention, "export_tlog", export_then_a_station_writes)
    out = prune(path, 1, CUT_US, tmp_path / "old.tlog")
    early = [r for r in ours if r[0] < CUT_US]
    assert out.frames == len(early) and (tmp_path / "old.tlog").read_bytes() == tlog_bytes(early)
    assert rows(path, 1) == [r for r in ours if r[0] >= CUT_US] + late


def test_a_reader_sees_the_frames_all_there_or_all_gone(archive, tmp_path):
    """A second station reading while the archive is pruned: its snapshot keeps every frame until it ends;
    the next one has none of the pruned."""
    path, ours, _ = archive
    reader = open_reader(path)
    reader.execute("BEGIN")
    before = reader.execute("SELECT count(*) FROM frames WHERE sysid = 1").fetchone()[0]
    out = prune(path, 1, CUT_US, None)
    assert reader.execute("SELECT count(*) FROM frames WHERE sysid = 1").fetchone()[0] == before == len(ours)
    reader.execute("COMMIT")
    after = reader.execute("SELECT count(*), min(t_us) FROM frames WHERE sysid = 1").fetchone()
    assert out.frames == len(ours) - after[0] > 0 and after[1] >= CUT_US
