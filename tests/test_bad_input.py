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
from ground import decode
from ground.decode import tlog_record
from ground.recording import Recording, RecordingError, read_recording, write_recording
from ground.tlog import TlogError, check_tlog

WALL0 = 1_750_000_000.0


def good_tlog(n=30) -> bytes:
    p = mavlink.MAVLink(None, srcSystem=FSW_SYSID, srcComponent=FSW_COMPID)
    out = b""
    for k in range(n):
        msg = mavlink.MAVLink_highres_imu_message(k * 100_000, 0, 0, 0, 0, 0, 0, 0.3, 0.1, -0.2, 0, 0, 0, 0, 0x1C0)
        msg.pack(p)
        p.seq = (p.seq + 1) % 256
        out += tlog_record(msg, WALL0 + 0.1 * k)
    return out


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
    assert check_tlog(tmp_path / "copy.tlog") == 30


@pytest.mark.parametrize("name, mutate, where, reason", [
    ("truncated frame", lambda d: d[:-5], "record 30 (byte", "truncated frame"),
    ("truncated time stamp", lambda d: d + b"\x00\x01\x02", "record 31 (byte", "truncated: 3 bytes left"),
    ("time stamp without frame", lambda d: d + struct.pack(">Q", int((WALL0 + 9) * 1e6)), "record 31",
     "without a frame"),
    ("time goes back", lambda d: d[RECORD:2 * RECORD] + d[:RECORD] + d[2 * RECORD:], "record 2 (byte",
     "time goes back"),
    ("not a tlog", lambda d: b"t_s,bx_uT,by_uT,bz_uT\n0,1,2,3\n", "record 1 (byte 0)", "not a tlog"),
    ("trailing noise", lambda d: d + struct.pack(">Q", int((WALL0 + 9) * 1e6)) + b"\x11" * 40, "record 31",
     "no record follows"),
    ("empty", lambda d: b"", "in.tlog", "empty file"),
])
def test_a_damaged_tlog_is_refused_with_its_place_and_no_output(tmp_path, capsys, name, mutate, where, reason):
    rc, err, outs = decode_cli(tmp_path, mutate(good_tlog()), capsys)
    assert rc == 1 and outs == []
    assert "in.tlog" in err and where in err and reason in err


def test_line_noise_recorded_inside_a_tlog_is_data_not_damage(tmp_path):
    d = good_tlog()
    noisy = d[:RECORD] + struct.pack(">Q", int((WALL0 + 0.05) * 1e6)) + bytes(range(1, 30)) + d[RECORD:]
    path = tmp_path / "noisy.tlog"
    path.write_bytes(noisy)
    assert check_tlog(path) == 31
    dec = decode.run(str(path), quiet=True)
    assert len(dec.recording()) == 30 and dec.stats.garbage_bytes > 0


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
        path = Path(__file__).resolve().parents[2] / "shared" / "data" / name
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
