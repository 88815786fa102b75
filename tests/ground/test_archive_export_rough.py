"""The archive's CSV export (accounting in bulk, rows held and written in batches) against the decoder fed
the same frames one by one, on a rough stream: what the box knew arriving and changing, truth appearing
late, estimates flagged or sent again, a lost, a copied, a corrupted and an unknown frame, a restart, a
second component."""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from fsw.telemetry.dialect import FSW_COMPID, FSW_SYSID, mavlink
from fsw.telemetry.framing import Deframer
from ground import decode
from ground.archive import ArchiveWriter, open_reader
from ground.archive.export import export_recordings
from ground.decode import Decoder
from ground.recorder import Recorder
from test_decode_knowledge import magcal, time_orbit, tle
from test_decode_recording import Box

WALL0_US = 1_750_000_000_000_000
_MAG = mavlink.MAVLINK_MSG_ID_DEBRIS_MAG_SAMPLE


def _msgid(frame: bytes) -> int:
    return frame[7] | frame[8] << 8 | frame[9] << 16


def rough_frames() -> list[tuple[int, bytes]]:
    """(receive time µs, frame) of 90 s of a box at 10 Hz with every irregularity the export must count."""
    rng = np.random.default_rng(18)
    box, other = Box(), Box(compid=FSW_COMPID + 1, run_id=0x5555)
    out: list[tuple[int, bytes]] = []
    restarted = False
    for k in range(900):
        t_s = 0.1 * k
        wall = WALL0_US + k * 100_000 + 40
        if k == 700 and not restarted:                       # the flight software restarts
            box, restarted = Box(run_id=0x4321), True
            box.p.seq = 77
        frames = []
        if k % 100 == 5:
            frames.append(time_orbit(box, t_s))
        if k % 200 == 10:
            frames.append(tle(box))
        if k % 100 == 0:
            frames.append(magcal(box, t_s, b_uT=(6.0 + k / 100, -9.0, 4.0),
                                 state=(mavlink.DEBRIS_MAGCAL_STATE_UNCERTAIN,
                                        mavlink.DEBRIS_MAGCAL_STATE_CONVERGED)[k // 100 % 2]))
        b = [0.3 + 0.01 * rng.normal(), 0.1, -0.2]
        kit_flags = mavlink.DEBRIS_SAMPLE_FLAGS_KIT_MOVING if 300 <= k < 320 else 0
        frames.append(box.pack(mavlink.MAVLink_debris_mag_sample_message(
            int(round(t_s * 1e6)), box.seq, box.run_id, b, kit_flags, [0.001 * (k % 7), 0.0, 0.0])))
        box.seq += 1
        flags = mavlink.DEBRIS_ESTIMATE_FLAGS_NO_ESTIMATE if k < 30 else 0
        frames.append(box.pack(mavlink.MAVLink_debris_rate_estimate_message(
            int(round(t_s * 1e6)), 0.1, 0.2, 0.3 + 1e-4 * k, 0.01, 0.01, 0.01, mavlink.DEBRIS_RATE_METHOD_BOER, flags)))
        if k >= 200:                                          # truth from 20 s on: the file is rewritten
            frames.append(box.truth(t_s))
        if k % 50 == 49 and k > 100:                          # an estimate sent again for a row long written
            frames.append(box.pack(mavlink.MAVLink_debris_rate_estimate_message(
                int(round((t_s - 5.0) * 1e6)), 9.0, 9.0, 9.0, 0.5, 0.5, 0.5, mavlink.DEBRIS_RATE_METHOD_BOER, 0)))
        if k % 30 == 0 and k < 300:
            frames.append(other.sample(t_s, gauss=0.5))
        out.extend((wall, f) for f in frames)
    lost = next(i for i, (t, _) in enumerate(out) if t >= WALL0_US + 30_000_000)
    del out[lost]
    dup = next(i for i, (t, _) in enumerate(out) if t >= WALL0_US + 40_000_000)
    out.insert(dup + 1, out[dup])
    bad = next(i for i, (t, f) in enumerate(out) if t >= WALL0_US + 50_000_000 and _msgid(f) == _MAG)   # a sample
    out[bad] = (out[bad][0], out[bad][1][:-1] + bytes([out[bad][1][-1] ^ 0x5A]))
    unk = next(i for i, (t, _) in enumerate(out) if t >= WALL0_US + 55_000_000)
    f = bytearray(out[unk][1])
    f[7:10] = (60_000).to_bytes(3, "little")                   # a message id no dialect here knows
    out[unk] = (out[unk][0], bytes(f))
    return out


@pytest.fixture(scope="module")
def rough(tmp_path_factory):
    d = tmp_path_factory.mktemp("rough")
    frames = rough_frames()
    (d / "in.tlog").write_bytes(b"".join(struct.pack(">Q", t) + f for t, f in frames))
    with ArchiveWriter(d / "a.sqlite") as w:
        for t, f in frames:
            w.add_frame(t, f[5], f[6], _msgid(f), None, f)
    return d, frames


def _without_source(path: Path) -> list[str]:
    return [ln for ln in path.read_text().splitlines() if not ln.startswith("# source:")]


def test_the_export_of_a_rough_stream_is_the_decoders_and_counts_every_rejection(rough, tmp_path):
    d, _ = rough
    assert decode.main([str(d / "in.tlog"), "--quiet", "--csv", str(tmp_path / "dec.csv"),
                        "--rates-csv", str(tmp_path / "dec_rates.csv")]) == 0
    whole = decode.run(str(d / "in.tlog"), quiet=True)
    out = export_recordings(open_reader(d / "a.sqlite"), FSW_SYSID, tmp_path / "ex.csv", tmp_path / "ex_rates.csv")
    made = sorted(p.name for p in tmp_path.glob("ex*.csv"))
    assert made == sorted(p.name.replace("dec", "ex", 1) for p in tmp_path.glob("dec*.csv"))
    assert len(made) == 6                      # two runs of the box and the second component, each two files
    for name in made:
        assert _without_source(tmp_path / name) == _without_source(tmp_path / name.replace("ex", "dec", 1)), name
    s, w = out.decoder.stats, whole.stats
    for src, stats in w.sources.items():
        mine, theirs = s.sources[src].as_dict(), stats.as_dict()
        for key in ("received", "duplicates", "late", "out_of_sequence", "samples", "first_s", "last_s"):
            assert mine[key] == theirs[key], (src, key)
    # every rejection counted: the corrupted sample and the unknown id. (The export decodes each archived
    # frame alone: a CRC mismatch is pymavlink's "malformed", the unknown id is seen as one and keeps
    # its place in the sequence; a stream's deframer calls both bad CRC and the second a loss.)
    assert (s.malformed, s.unknown, s.bad_crc) == (1, 1, 0) and (w.bad_crc, w.unknown) == (2, 0)
    assert s.sources[(FSW_SYSID, FSW_COMPID)].duplicates == 1
    assert s.sources[(FSW_SYSID, FSW_COMPID)].lost == w.sources[(FSW_SYSID, FSW_COMPID)].lost - 1
    known = {k: n for k, n in whole.frames_by_type.items() if k != "BAD_DATA"}
    assert out.decoder.frames_by_type == known | {"BAD_DATA": 1, "UNKNOWN_60000": 1}
    # the second run's file was written as it settled: what the box knew restated between the rows
    lines = (tmp_path / "ex.1-191.run2.csv").read_text().splitlines()
    first_row = next(i for i, ln in enumerate(lines) if ln[0].isdigit())
    assert any(ln.startswith("# magcal_state:") for ln in lines[first_row:])


@pytest.mark.parametrize("hold_rows", [1, 7, 10**6])
def test_rows_held_give_the_same_files_as_rows_written_as_they_settle(rough, tmp_path, hold_rows):
    _, frames = rough
    written = {}
    for hold in (0, hold_rows):
        base = tmp_path / f"h{hold}"
        base.mkdir()
        dec = Decoder(recorder=Recorder(base / "r.csv", base / "r_rates.csv", hold_rows=hold))
        deframer = Deframer()
        for t_us, f in frames:
            for m in deframer.feed(f, end=True):
                dec.handle(m, t_us * 1e-6)
        dec.finish()
        written[hold] = {p.name: p.read_bytes() for p in sorted(base.iterdir())}
    assert len(written[0]) == 6 and written[hold_rows] == written[0]
