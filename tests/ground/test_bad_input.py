"""Bad input to the ground tools: damaged .tlog files and CSVs in the wrong units give a clear error
naming the file and where in it, a non-zero exit status and no output file. (Malformed CSV cells,
rows and headers: tests/test_recording.py.)"""
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fsw.telemetry.dialect import FSW_COMPID, FSW_SYSID, mavlink
from fsw.telemetry.signing import SigningClock, setup_outgoing, unix_to_timestamp
from ground import decode
from ground.decode import tlog_record
from ground.recording import Recording, RecordingError, read_recording, write_recording
from ground.tlog import TlogError, check_tlog, read_tlog
from support import SHARED_DATA, WALL0, good_tlog

RECORD = len(good_tlog(1))


def decode_cli(tmp_path: Path, data: bytes, capsys):
    src = tmp_path / "in.tlog"
    src.write_bytes(data)
    outs = [tmp_path / "out.csv", tmp_path / "rates.csv", tmp_path / "copy.tlog"]
    rc = decode.main([str(src), "--quiet", "--csv", str(outs[0]), "--rates-csv", str(outs[1]),
                      "--tlog", str(outs[2])])
    return rc, capsys.readouterr().err, [p for p in outs if p.exists()]


def test_a_good_tlog_decodes(tmp_path, capsys):
    rc, err, outs = decode_cli(tmp_path, good_tlog(), capsys)
    assert rc == 0 and err == "" and len(outs) == 3
    assert len(read_recording(tmp_path / "out.csv")) == 30
    report = check_tlog(tmp_path / "copy.tlog")
    assert report.records == 30 and not report.damaged


def junk(n, seed=1) -> bytes:
    """`n` bytes of seeded noise without a start byte (so that no frame can begin inside them)."""
    rng = np.random.default_rng(seed)
    return bytes(int(x) for x in rng.integers(0, 0xFD, n))


def flip_length(d: bytes, k: int, new_len: int) -> bytes:
    """Record k (0-based) with its frame's length byte set to `new_len`."""
    b = bytearray(d)
    b[k * RECORD + 8 + 1] = new_len
    return bytes(b)


def swap(d: bytes, k: int) -> bytes:
    """Records k and k + 1 exchanged: the time stamp goes back once."""
    return d[:k * RECORD] + d[(k + 1) * RECORD:(k + 2) * RECORD] + d[k * RECORD:(k + 1) * RECORD] + d[(k + 2) * RECORD:]


STAMP = struct.pack(">Q", int((WALL0 + 9) * 1e6))
DAYS_30 = 30 * 86400


def restamp(d: bytes, k: int, t_s: float) -> bytes:
    """Record k with its time stamp set to WALL0 + t_s (a damaged time stamp that reads as another date)."""
    return d[:k * RECORD] + struct.pack(">Q", int((WALL0 + t_s) * 1e6)) + d[k * RECORD + 8:]


def all_at_once(d: bytes) -> bytes:
    """57 junk bytes first, records 3 and 4 swapped, 20 junk bytes before record 12, record 20's length
    damaged, the last record cut by 7 bytes."""
    d = flip_length(swap(d, 3), 20, 9)
    return junk(57) + d[:12 * RECORD] + junk(20, 2) + d[12 * RECORD:-7]


# (name, damage, records kept = samples in the CSV, report counts: junk, damaged, cut bytes, time back)
@pytest.mark.parametrize("name, mutate, kept, counts", [
    ("cut last frame", lambda d: d[:-5], 29, dict(cut_bytes=RECORD - 5)),
    ("cut time stamp", lambda d: d + b"\x00\x01\x02", 30, dict(cut_bytes=3)),
    ("time stamp without frame", lambda d: d + STAMP, 30, dict(cut_bytes=8)),
    ("57 junk bytes inside", lambda d: d[:5 * RECORD] + junk(57) + d[5 * RECORD:], 30, dict(junk_bytes=57)),
    ("57 junk bytes first", lambda d: junk(57) + d, 30, dict(junk_bytes=57)),
    ("length byte too large", lambda d: flip_length(d, 10, 200), 29, dict(damaged_records=1)),
    ("length byte too small", lambda d: flip_length(d, 10, 3), 29, dict(damaged_records=1)),
    ("length byte past the end", lambda d: flip_length(d, 28, 255), 29, dict(damaged_records=1)),
    ("two time stamps out of order", lambda d: swap(d, 0), 30, dict(time_back=1)),
    ("all at once", lambda d: all_at_once(d), 28, dict(junk_bytes=77, damaged_records=1, cut_bytes=RECORD - 7,
                                                     time_back=1)),
    # found by the fuzz (tests/test_fuzz_readers.py): these lost every record after the first, or one
    ("first time stamp days off", lambda d: restamp(d, 0, DAYS_30), 30, dict(time_back=1)),
    ("a time stamp days ahead", lambda d: restamp(d, 10, DAYS_30), 30, dict(time_jumps=1, time_back=1)),
    ("a time stamp without its frame inside", lambda d: d[:5 * RECORD] + STAMP + d[5 * RECORD:], 30,
     dict(junk_bytes=8)),
    ("a record cut to 7 bytes of its time stamp", lambda d: d[:5 * RECORD + 7] + d[6 * RECORD:], 29,
     dict(junk_bytes=7)),
])
def test_a_damaged_tlog_keeps_every_intact_record_and_reports_the_rest(tmp_path, capsys, name, mutate, kept, counts):
    data = mutate(good_tlog())
    src = tmp_path / "in.tlog"
    src.write_bytes(data)
    report = check_tlog(src)
    assert report.records == kept and report.damaged
    for what in ("junk_bytes", "damaged_records", "cut_bytes", "time_back", "time_jumps"):
        assert getattr(report, what) == counts.get(what, 0), what
    if "damaged_records" in counts:
        assert report.damaged_bytes > 0
    rc, err, outs = decode_cli(tmp_path, data, capsys)
    assert rc == 0 and len(outs) == 3 and src.read_bytes() == data
    assert len(read_recording(tmp_path / "out.csv")) == kept
    assert check_tlog(tmp_path / "copy.tlog").records == kept      # the copy holds the intact frames only


def mixed_tlog(n=20, key: bytes | None = None) -> tuple[bytes, list[int]]:
    """Records of alternately a HIGHRES_IMU frame (long) and a HEARTBEAT (short), signed with `key` when
    given; and each record's offset."""
    p = mavlink.MAVLink(None, srcSystem=FSW_SYSID, srcComponent=FSW_COMPID)
    if key is not None:
        setup_outgoing(p, key, SigningClock(epoch=unix_to_timestamp(WALL0)))
    out, offsets = b"", []
    for k in range(n):
        msg = mavlink.MAVLink_highres_imu_message(k * 100_000, 0, 0, 0, 0, 0, 0, 0.3, 0.1, -0.2, 0, 0, 0, 0, 0x1C0) \
            if k % 2 == 0 else mavlink.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3)
        msg.pack(p)
        p.seq = (p.seq + 1) % 256
        offsets.append(len(out))
        out += tlog_record(msg, WALL0 + 0.1 * k)
    return out, offsets


def kept_times(path) -> list[int]:
    return [r.t_us for r in read_tlog(path)]


def test_a_signed_frame_cut_inside_its_signature_does_not_take_the_next_record(tmp_path):
    """Found by the fuzz: the signature block is not covered by the CRC, so a signed frame that lost its
    last byte still "checked" with the next record's first byte as its own, and that record was lost."""
    d, offsets = mixed_tlog(key=bytes(range(7, 39)))
    cut = offsets[6] - 1                          # record 5 (a heartbeat) loses the last byte of its signature
    path = tmp_path / "signed.tlog"
    path.write_bytes(d[:cut] + d[cut + 1:])
    everything = kept_times_of(d, tmp_path)
    assert kept_times(path) == everything[:5] + everything[6:]
    report = check_tlog(path)
    assert report.damaged_records == 1 and report.damaged_bytes == offsets[6] - offsets[5] - 1


def test_a_damaged_frame_ending_where_a_record_starts_does_not_hide_one_inside_it(tmp_path):
    """Found by the fuzz: a long frame that lost exactly the length of the short record after it ended
    where the record after that starts, and was kept with the intact short record inside it."""
    d, offsets = mixed_tlog()
    length = offsets[6] - offsets[5]                # record 5, a heartbeat
    start = offsets[4] + 20                         # inside record 4's payload, a HIGHRES_IMU
    assert offsets[5] - start > length
    path = tmp_path / "cut.tlog"
    path.write_bytes(d[:start] + d[start + length:])
    everything = kept_times_of(d, tmp_path)
    assert kept_times(path) == everything[:4] + everything[5:]


def kept_times_of(data: bytes, tmp_path) -> list[int]:
    path = tmp_path / "whole.tlog"
    path.write_bytes(data)
    return kept_times(path)


def test_any_one_flipped_bit_of_a_length_byte_loses_that_record_only(tmp_path):
    d = good_tlog()
    path = tmp_path / "flipped.tlog"
    for k in range(30):
        for bit in range(8):
            b = bytearray(d)
            b[k * RECORD + 8 + 1] ^= 1 << bit
            path.write_bytes(bytes(b))
            report = check_tlog(path)
            assert report.records == 29 and report.damaged_records + bool(report.cut_bytes) == 1, (k, bit)


def test_the_report_says_where_and_that_records_follow(tmp_path, capsys):
    """The case: junk early in a long file was reported as "no record follows" although
    hundreds did, and the whole file was refused."""
    d = good_tlog(320)
    data = d[:2 * RECORD] + junk(57) + d[2 * RECORD:]
    rc, err, outs = decode_cli(tmp_path, data, capsys)
    assert rc == 0 and len(read_recording(tmp_path / "out.csv")) == 320
    report = check_tlog(tmp_path / "in.tlog")
    assert report.records == 320
    assert report.events == [f"byte {2 * RECORD}: 57 bytes in no record"]
    assert "320 records kept; 57 bytes in no record (1 run) skipped" in report.text()


def test_the_damage_is_reported_in_the_summary(tmp_path, capsys):
    src = tmp_path / "in.tlog"
    src.write_bytes(good_tlog() + STAMP)
    assert decode.main([str(src), "--quiet", "--csv", str(tmp_path / "o.csv")]) == 0
    out = capsys.readouterr().out
    line = next(x for x in out.splitlines() if x.startswith("damaged tlog:"))
    assert "30 records kept" in line and "cut short" in line and f"byte {30 * RECORD}" in line


@pytest.mark.parametrize("name, data, reason", [
    ("not a tlog", b"t_s,bx_uT,by_uT,bz_uT\n0,1,2,3\n", "not a tlog: no record found"),
    ("only junk", junk(500), "not a tlog: no record found"),
    ("empty", b"", "empty file"),
], ids=["not a tlog", "only junk", "empty"])
def test_a_file_with_nothing_intact_is_refused_and_nothing_written(tmp_path, capsys, name, data, reason):
    rc, err, outs = decode_cli(tmp_path, data, capsys)
    assert rc == 1 and outs == []
    assert "in.tlog" in err and reason in err and len(err.strip().splitlines()) == 1
    with pytest.raises(TlogError, match=reason):
        check_tlog(tmp_path / "in.tlog")


def test_line_noise_recorded_inside_a_tlog_is_data_not_damage(tmp_path):
    d = good_tlog()
    noisy = d[:RECORD] + struct.pack(">Q", int((WALL0 + 0.05) * 1e6)) + bytes(range(1, 30)) + d[RECORD:]
    path = tmp_path / "noisy.tlog"
    path.write_bytes(noisy)
    report = check_tlog(path)
    assert report.records == 31 and report.noise_records == 1 and not report.damaged
    dec = decode.run(str(path), quiet=True)
    assert len(dec.recording()) == 30 and dec.stats.garbage_bytes > 0


def test_trailing_noise_after_a_time_stamp_is_a_noise_record(tmp_path):
    path = tmp_path / "t.tlog"
    path.write_bytes(good_tlog() + STAMP + b"\x11" * 40)
    report = check_tlog(path)
    assert report.records == 31 and report.noise_records == 1 and not report.damaged


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_any_damage_to_a_tlog_is_decoded_or_refused_cleanly(tmp_path, data):
    d = bytearray(good_tlog(10))
    for _ in range(data.draw(st.integers(1, 4))):
        op = data.draw(st.sampled_from(["flip", "cut", "insert"]))
        i = data.draw(st.integers(0, max(len(d) - 1, 0)))
        if op == "flip" and d:
            d[i] ^= data.draw(st.integers(1, 255))
        elif op == "cut":
            del d[i:i + data.draw(st.integers(1, 40))]
        else:
            d[i:i] = data.draw(st.binary(min_size=1, max_size=20))
    src = tmp_path / "f.tlog"
    out = tmp_path / "f.csv"
    out.unlink(missing_ok=True)
    src.write_bytes(bytes(d))
    try:
        dec = decode.run(str(src), quiet=True, csv=out)
    except (TlogError, RecordingError):
        assert not out.exists()
    else:
        assert out.exists() and len(read_recording(out)) == len(dec.recording())


def field_file(tmp_path, scale):
    t = np.arange(50) * 0.1
    b = np.column_stack([np.cos(t), np.sin(t), np.full_like(t, 0.5)]) * 40e-6 * scale
    path = tmp_path / "f.csv"
    write_recording(path, Recording(t_s=t, b_T=b))
    return path


@pytest.mark.parametrize("scale, looks_like", [(1e-6, "tesla or gauss"), (1e-2, "tesla or gauss"), (1e3, "nT")])
def test_field_in_the_wrong_units_is_refused_when_checked(tmp_path, scale, looks_like):
    path = field_file(tmp_path, scale)
    with pytest.raises(RecordingError) as e:
        read_recording(path, check_units=True)
    assert e.value.path == str(path) and e.value.line == 2 and e.value.column == "bx_uT"
    assert looks_like in str(e.value)
    read_recording(path)                               # the format itself allows any value


def test_field_in_microtesla_passes_the_check(tmp_path):
    assert len(read_recording(field_file(tmp_path, 1.0), check_units=True)) == 50
    for name in ("broad_02_undisturbed_slow_rotation_B.csv", "xio_fusion_sensor_data.csv"):
        path = SHARED_DATA / name
        if path.exists():
            read_recording(path, check_units=True)


def test_truncated_and_non_monotonic_csv_name_their_line(tmp_path):
    path = field_file(tmp_path, 1.0)
    text = path.read_text()
    cut = tmp_path / "cut.csv"
    cut.write_text(text[: text.rindex(",")])           # the last row loses its last cell
    with pytest.raises(RecordingError, match=r"cut\.csv:51: column 'bz_uT'"):
        read_recording(cut)
    lines = text.splitlines()
    lines[10], lines[11] = lines[11], lines[10]
    back = tmp_path / "back.csv"
    back.write_text("\n".join(lines) + "\n")
    with pytest.raises(RecordingError, match=r"back\.csv:12: column 't_s': time .* not after"):
        read_recording(back)


def test_signed_frames_whose_signature_ends_in_a_start_byte_are_intact_records(tmp_path):
    """A start byte in a signed frame's last bytes may begin a frame cut in two by a read (the
    deframer looks at those bytes again on a stream); a tlog record is whole: the frame is intact."""
    p = mavlink.MAVLink(None, srcSystem=FSW_SYSID, srcComponent=FSW_COMPID)
    clock = SigningClock(epoch=unix_to_timestamp(WALL0))
    setup_outgoing(p, bytes(range(7, 39)), clock)
    out, kept = b"", 0
    for _ in range(3000):
        frame = mavlink.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3).pack(p)
        p.seq = (p.seq + 1) % 256
        if 0xFD in frame[-9:]:
            out += struct.pack(">Q", int((WALL0 + 0.1 * kept) * 1e6)) + frame
            kept += 1
    path = tmp_path / "fd.tlog"
    path.write_bytes(out)
    report = check_tlog(path)
    assert kept > 50 and report.records == kept and not report.damaged
