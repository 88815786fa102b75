"""Recording format v1 (docs/spec/recording-format.md): the real data files, units at the edge, every
rejection rule with its line and column, atomic writes, and property tests (round trip; corrupted
files give a valid recording or a RecordingError, never anything else, never a dropped row)."""
from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ground.recording import (RateEstimates, Recording, RecordingError, read_rate_estimates,
                              read_recording, write_rate_estimates, write_recording)
from support import SHARED_DATA

# the project's shared data folder sits beside the repository (../shared/data)
DATA = SHARED_DATA
HEADER = "t_s,bx_uT,by_uT,bz_uT"


def _write(tmp_path: Path, text: str | bytes, name: str = "r.csv") -> Path:
    p = tmp_path / name
    p.write_bytes(text.encode() if isinstance(text, str) else text)
    return p


def _data_lines(text: str) -> int:
    """Rows the format says the text holds: non-comment, non-blank lines after the header."""
    lines = [ln.rstrip("\r") for ln in text.split("\n")]
    return max(0, sum(1 for ln in lines if ln.strip() and not ln.startswith("#")) - 1)


# --- the real recordings in ../shared/data --------------------------------------------------------

REAL = [("broad_02_undisturbed_slow_rotation_B.csv", 202.0),
        ("broad_09_undisturbed_fast_rotation_with_breaks_B.csv", 202.0),
        ("broad_30_disturbed_stationary_magnet_C.csv", 202.0),
        ("xio_fusion_sensor_data.csv", 19.8)]


@pytest.mark.parametrize("name,rate_hz", REAL)
def test_reads_the_real_recordings(name: str, rate_hz: float) -> None:
    path = DATA / name
    if not path.exists():
        pytest.skip(f"{path} not present")
    rec = read_recording(path)
    n = _data_lines(path.read_text())
    assert len(rec) == n > 1000
    assert rec.b_T.shape == (n, 3) and rec.m_Nm.shape == (n, 3) and rec.w_ref_radps.shape == (n, 3)
    assert np.all(np.diff(rec.t_s) > 0)
    assert not rec.m_Nm.any()  # no moment columns: zeros
    # mean sample rate (README: ~202 Hz BROAD, ~20 Hz x-io)
    assert n / (rec.t_s[-1] - rec.t_s[0]) == pytest.approx(rate_hz, rel=0.02)
    # the lab's field, ~44 µT, read as tesla
    b_uT = np.linalg.norm(rec.b_T, axis=1) * 1e6
    assert np.median(b_uT) == pytest.approx(44.0, abs=1.0)
    # gyro reference in rad/s: hand-moved sensor, below 30 rad/s, not all zero
    w = np.linalg.norm(rec.w_ref_radps, axis=1)
    assert 0.1 < w.max() < 30.0
    assert "source" in rec.metadata and "licence" in rec.metadata
    assert rec.path == path


def test_first_row_of_a_real_file_in_si_units() -> None:
    path = DATA / "broad_02_undisturbed_slow_rotation_B.csv"
    if not path.exists():
        pytest.skip(f"{path} not present")
    rec = read_recording(path)
    # 0.00000,0.406,16.163,-42.705,0.183,0.183,0.000
    np.testing.assert_allclose(rec.b_T[0], [0.406e-6, 16.163e-6, -42.705e-6], rtol=1e-15)
    np.testing.assert_allclose(rec.w_ref_radps[0], np.array([0.183, 0.183, 0.0]) * math.pi / 180,
                               rtol=1e-15)
    assert rec.metadata["source"].startswith("BROAD benchmark")


# --- reading rules ---------------------------------------------------------------------------

def test_units_metadata_extra_columns_and_order(tmp_path: Path) -> None:
    text = ("# source: unit test\n"
            "# mass_kg: 530\n"
            "# a comment without a key\n"
            "#source: second line\n"
            "\n"
            "note,bz_uT,t_s,by_uT,bx_uT,wx_dps,wy_dps,wz_dps,mx_Nm,my_Nm,mz_Nm\n"
            "a,3,0.0,2,1,180,-90,0,0.5,0,0\n"
            "b,-44,0.5,0,0.25,,nan,NaN,,0,0\n")
    rec = read_recording(_write(tmp_path, text))
    np.testing.assert_array_equal(rec.t_s, [0.0, 0.5])
    np.testing.assert_allclose(rec.b_T, [[1e-6, 2e-6, 3e-6], [0.25e-6, 0.0, -44e-6]], rtol=1e-15)
    np.testing.assert_allclose(rec.w_ref_radps[0], [math.pi, -math.pi / 2, 0.0], rtol=1e-15)
    assert np.isnan(rec.w_ref_radps[1]).all()  # unknown reference: NaN, the row kept
    np.testing.assert_array_equal(rec.m_Nm[0], [0.5, 0.0, 0.0])
    assert np.isnan(rec.m_Nm[1, 0])
    assert rec.metadata == {"source": "unit test\nsecond line", "mass_kg": "530"}


def test_a_key_restated_after_the_header_replaces_its_value(tmp_path: Path) -> None:
    text = ("# source: unit test\n# utc0: 2026-11-21T12:00:00Z\n# source: second line\n"
            "t_s,bx_uT,by_uT,bz_uT\n0,1,2,3\n"
            "# utc0: 2026-11-21T12:00:03Z\n# note: one\n# note: two\n"
            "1,1,2,3\n# source: appended\n")
    rec = read_recording(_write(tmp_path, text))
    assert len(rec) == 2
    assert rec.metadata == {"source": "appended", "utc0": "2026-11-21T12:00:03Z", "note": "one\ntwo"}


def test_absent_optional_columns(tmp_path: Path) -> None:
    rec = read_recording(_write(tmp_path, f"{HEADER}\n0,1,2,3\n1,1,2,3\n"))
    assert rec.w_ref_radps is None
    np.testing.assert_array_equal(rec.m_Nm, np.zeros((2, 3)))


def test_header_only_is_an_empty_recording(tmp_path: Path) -> None:
    rec = read_recording(_write(tmp_path, f"# source: nothing yet\n{HEADER}\n"))
    assert len(rec) == 0 and rec.b_T.shape == (0, 3)


def test_crlf_bom_and_padded_cells(tmp_path: Path) -> None:
    rec = read_recording(_write(tmp_path, f"\ufeff{HEADER}\r\n 0 , 1,2 ,3\r\n1,1,2,3\r\n"))
    np.testing.assert_array_equal(rec.b_T[0] * 1e6, [1.0, 2.0, 3.0])


BAD = [  # (data rows after the header, line of the error, column)
    ("0,1,2,3\n1,1,,3\n", 3, "by_uT"),
    ("0,1,2,3\n1,1,2,abc\n", 3, "bz_uT"),
    ("0,1,2,3\n1,nan,2,3\n", 3, "bx_uT"),
    ("0,1,2,3\n1,1,inf,3\n", 3, "by_uT"),
    ("0,1,2,-Infinity\n", 2, "bz_uT"),
    ("0,1,2,1e999\n", 2, "bz_uT"),
    ("0,1,2,1_0\n", 2, "bz_uT"),
    ("0,1,2,0x10\n", 2, "bz_uT"),
    ("0,1,2,3\n0,1,2,3\n", 3, "t_s"),
    ("0,1,2,3\n1,1,2,3\n0.5,1,2,3\n", 4, "t_s"),
    ("nan,1,2,3\n", 2, "t_s"),
    (",1,2,3\n", 2, "t_s"),
    ("0,1,2,3\n1,1,2\n", 3, "bz_uT"),
    ("0,1,2,3,4\n", 2, None),
    ('0,1,2,"3\n', 2, None),
]


@pytest.mark.parametrize("rows,line,column", BAD)
def test_rejections_name_file_line_and_column(tmp_path: Path, rows: str, line: int, column) -> None:
    path = _write(tmp_path, f"{HEADER}\n{rows}")
    with pytest.raises(RecordingError) as err:
        read_recording(path)
    assert (err.value.path, err.value.line, err.value.column) == (str(path), line, column)
    assert str(err.value).startswith(f"{path}:{line}")
    assert isinstance(err.value, ValueError)


@pytest.mark.parametrize("text,line,column", [
    ("t_s,bx_uT,by_uT\n0,1,2\n", 1, "bz_uT"),                        # required column missing
    (f"# x: y\n{HEADER},wx_dps,wy_dps\n0,1,2,3,0,0\n", 2, "wz_dps"),  # incomplete optional triad
    (f"{HEADER},bx_uT\n0,1,2,3,4\n", 1, "bx_uT"),                     # duplicate column
    (f"{HEADER},wx_dps,wy_dps,wz_dps\n0,1,2,3,0,inf,0\n", 2, "wy_dps"),  # inf even where NaN is ok
    (f"{HEADER},wx_dps,wy_dps,wz_dps\n0,1,2,3,0,fast,0\n", 2, "wy_dps"),
    ("# only comments\n\n", None, None),
])
def test_header_and_optional_column_rejections(tmp_path: Path, text: str, line, column) -> None:
    with pytest.raises(RecordingError) as err:
        read_recording(_write(tmp_path, text))
    assert (err.value.line, err.value.column) == (line, column)


def test_invalid_utf8_names_its_line(tmp_path: Path) -> None:
    path = _write(tmp_path, f"# source: x\n{HEADER}\n0,1,2,3\n".encode() + b"1,1,\xff,3\n")
    with pytest.raises(RecordingError) as err:
        read_recording(path)
    assert err.value.line == 4


def test_missing_file_is_a_recording_error(tmp_path: Path) -> None:
    with pytest.raises(RecordingError):
        read_recording(tmp_path / "absent.csv")


# --- writing ---------------------------------------------------------------------------------

def _rec(n: int = 3, **kw) -> Recording:
    t = np.arange(n) * 0.1
    b = np.tile([20e-6, -5e-6, 40e-6], (n, 1))
    return Recording(t_s=t, b_T=b, **kw)


def test_write_is_readable_with_header_and_units(tmp_path: Path) -> None:
    rec = _rec(2, w_ref_radps=np.array([[math.pi, 0, 0], [0, 0, -math.pi / 2]]),
               m_Nm=np.array([[0.0, 0.0, 0.0], [0.0, 0.2, 0.0]]), metadata={"source": "sitl", "mass_kg": "530"})
    path = tmp_path / "out.csv"
    write_recording(path, rec)
    lines = path.read_text().splitlines()
    assert lines[:3] == ["# source: sitl", "# mass_kg: 530",
                         "t_s,bx_uT,by_uT,bz_uT,mx_Nm,my_Nm,mz_Nm,wx_dps,wy_dps,wz_dps"]
    assert [float(x) for x in lines[3].split(",")] == pytest.approx([0, 20, -5, 40, 0, 0, 0, 180, 0, 0])
    back = read_recording(path)
    np.testing.assert_allclose(back.w_ref_radps, rec.w_ref_radps, rtol=1e-14)
    assert back.metadata == rec.metadata


def test_zero_moment_and_no_reference_columns_are_not_written(tmp_path: Path) -> None:
    path = tmp_path / "out.csv"
    write_recording(path, _rec())
    assert path.read_text().splitlines()[0] == HEADER


@pytest.mark.parametrize("mutate,line,column", [
    (lambda r: r.b_T.__setitem__((2, 1), np.nan), 4 + 2, "by_uT"),
    (lambda r: r.b_T.__setitem__((0, 2), np.inf), 4 + 0, "bz_uT"),
    (lambda r: r.t_s.__setitem__(1, 0.0), 4 + 1, "t_s"),
    (lambda r: r.w_ref_radps.__setitem__((1, 0), -np.inf), 4 + 1, "wx_dps"),
])
def test_write_refuses_what_the_reader_would_reject(tmp_path: Path, mutate, line: int, column: str) -> None:
    path = tmp_path / "out.csv"
    path.write_text("previous content\n")
    rec = _rec(3, w_ref_radps=np.zeros((3, 3)), metadata={"source": "x\ny"})  # 2 comment lines + header
    mutate(rec)
    with pytest.raises(RecordingError) as err:
        write_recording(path, rec)
    assert (err.value.line, err.value.column) == (line, column)
    assert path.read_text() == "previous content\n"  # nothing written
    assert os.listdir(tmp_path) == ["out.csv"]           # no temporary file left


def test_recording_checks_shapes() -> None:
    with pytest.raises(ValueError):
        Recording(t_s=np.arange(3.0), b_T=np.zeros((2, 3)))


# --- rate estimates --------------------------------------------------------------------------

def test_rate_estimates_round_trip_with_nan(tmp_path: Path) -> None:
    w = np.array([[np.nan] * 3, [0.1, -0.2, 0.3], [1.0, 2.0, 3.0]])
    s = np.array([[np.nan] * 3, [0.01, 0.02, 0.03], [0.0, 0.0, 0.0]])
    est = RateEstimates(t_s=[0.0, 1.0, 2.0], w_radps=w, sigma_radps=s, metadata={"method": "boer"})
    path = tmp_path / "rates.csv"
    write_rate_estimates(path, est)
    lines = path.read_text().splitlines()
    assert lines[1] == "t_s,wx_dps,wy_dps,wz_dps,sx_dps,sy_dps,sz_dps"
    assert lines[2] == "0.0,nan,nan,nan,nan,nan,nan"
    back = read_rate_estimates(path)
    np.testing.assert_allclose(back.w_radps, w, rtol=1e-14)
    np.testing.assert_allclose(back.sigma_radps, s, rtol=1e-14)
    assert back.metadata == {"method": "boer"}


@pytest.mark.parametrize("row,column", [("0,1,2,3,-1,0,0", "sx_dps"), ("nan,1,2,3,0,0,0", "t_s"),
                                        ("0,1,inf,3,0,0,0", "wy_dps")])
def test_rate_estimates_rejections(tmp_path: Path, row: str, column: str) -> None:
    path = _write(tmp_path, f"t_s,wx_dps,wy_dps,wz_dps,sx_dps,sy_dps,sz_dps\n{row}\n")
    with pytest.raises(RecordingError) as err:
        read_rate_estimates(path)
    assert (err.value.line, err.value.column) == (2, column)


def test_rate_estimates_write_refuses_negative_sigma(tmp_path: Path) -> None:
    est = RateEstimates(t_s=[0.0], w_radps=np.zeros((1, 3)), sigma_radps=[[0.0, -1.0, 0.0]])
    with pytest.raises(RecordingError) as err:
        write_rate_estimates(tmp_path / "r.csv", est)
    assert (err.value.line, err.value.column) == (2, "sy_dps")
    assert not (tmp_path / "r.csv").exists()


# --- properties ------------------------------------------------------------------------------

finite = st.floats(min_value=-1e3, max_value=1e3, allow_nan=False, allow_infinity=False)


@st.composite
def recordings(draw) -> Recording:
    n = draw(st.integers(1, 12))
    steps = draw(st.lists(st.floats(1e-6, 10.0), min_size=n, max_size=n))
    t0 = draw(st.floats(-1e3, 1e3))
    t = t0 + np.cumsum(steps)
    if not np.all(np.diff(t) > 0):
        t = t0 + np.arange(1, n + 1, dtype=float)
    b = np.array(draw(st.lists(st.tuples(finite, finite, finite), min_size=n, max_size=n))) * 1e-6
    m = w = None
    if draw(st.booleans()):
        m = np.array(draw(st.lists(st.tuples(finite, finite, finite), min_size=n, max_size=n)))
    if draw(st.booleans()):
        w = np.array(draw(st.lists(st.tuples(finite, finite, finite), min_size=n, max_size=n)))
    keys = draw(st.lists(st.from_regex(r"[a-z_][a-z0-9_]{0,8}", fullmatch=True), max_size=3, unique=True))
    meta = {k: draw(st.text(st.characters(min_codepoint=32, max_codepoint=0x2FF), max_size=20)).strip()
            for k in keys}
    return Recording(t_s=t, b_T=b, m_Nm=m, w_ref_radps=w, metadata=meta)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rec=recordings())
def test_write_read_round_trip(tmp_path: Path, rec: Recording) -> None:
    path = tmp_path / "rt.csv"
    write_recording(path, rec)
    back = read_recording(path)
    np.testing.assert_array_equal(back.t_s, rec.t_s)  # time is written in its own unit: exact
    np.testing.assert_allclose(back.b_T, rec.b_T, rtol=1e-14, atol=1e-30)
    np.testing.assert_allclose(back.m_Nm, rec.m_Nm, rtol=1e-14, atol=0)
    if rec.w_ref_radps is None:
        assert back.w_ref_radps is None
    else:
        np.testing.assert_allclose(back.w_ref_radps, rec.w_ref_radps, rtol=1e-14, atol=1e-300)
    assert back.metadata == rec.metadata


def _valid_text(rec: Recording, tmp_path: Path) -> str:
    path = tmp_path / "v.csv"
    write_recording(path, rec)
    return path.read_text()


@st.composite
def corruptions(draw, text: str) -> bytes:
    """Byte-level damage: insert, delete, replace, duplicate or drop a line, truncate."""
    data = bytearray(text.encode())
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["insert", "delete", "replace", "dup_line", "drop_line", "truncate"]))
        pos = draw(st.integers(0, max(0, len(data) - 1)))
        if kind == "insert":
            data[pos:pos] = draw(st.binary(min_size=1, max_size=4)
                                 | st.sampled_from([b",", b"\n", b"#", b"-", b".", b"e", b"nan", b'"', b"\r", b" "]))
        elif kind == "delete" and data:
            del data[pos:pos + draw(st.integers(1, 3))]
        elif kind == "replace" and data:
            data[pos] = draw(st.integers(0, 255))
        elif kind in ("dup_line", "drop_line"):
            lines = bytes(data).split(b"\n")
            i = draw(st.integers(0, len(lines) - 1))
            if kind == "dup_line":
                lines.insert(i, lines[i])
            else:
                del lines[i]
            data = bytearray(b"\n".join(lines))
        elif kind == "truncate":
            del data[pos:]
    return bytes(data)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data(), rec=recordings())
def test_corrupted_file_gives_valid_recording_or_recording_error(tmp_path: Path, data, rec: Recording) -> None:
    bad = data.draw(corruptions(_valid_text(rec, tmp_path)))
    path = _write(tmp_path, bad, "bad.csv")
    try:
        got = read_recording(path)
    except RecordingError as e:
        assert e.path == str(path)
        return
    # Accepted: it must obey every rule, and hold every row the damaged text holds.
    assert np.all(np.isfinite(got.t_s)) and np.all(np.diff(got.t_s) > 0)
    assert np.all(np.isfinite(got.b_T))
    assert not np.isinf(got.m_Nm).any()
    assert len(got) == _data_lines(bad.decode("utf-8-sig"))


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data(), rec=recordings())
def test_a_bad_required_cell_is_found_at_its_line_and_column(tmp_path: Path, data, rec: Recording) -> None:
    lines = _valid_text(rec, tmp_path).split("\n")
    header_i = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    names = lines[header_i].split(",")
    row = data.draw(st.integers(0, len(rec) - 1))
    col = data.draw(st.sampled_from(["t_s", "bx_uT", "by_uT", "bz_uT"]))
    cell = data.draw(st.sampled_from(["", " ", "x", "nan", "NaN", "inf", "-inf", "1e400", "1_0",
                                      "0x1", "--1", "1.2.3", "\u0663"]))
    cells = lines[header_i + 1 + row].split(",")
    cells[names.index(col)] = cell
    lines[header_i + 1 + row] = ",".join(cells)
    path = _write(tmp_path, "\n".join(lines), "bad.csv")
    with pytest.raises(RecordingError) as err:
        read_recording(path)
    assert (err.value.line, err.value.column) == (header_i + 2 + row, col)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data(), rec=recordings())
def test_harmless_changes_give_the_same_data(tmp_path: Path, data, rec: Recording) -> None:
    """Comment and blank lines anywhere, an extra column: the same data."""
    lines = _valid_text(rec, tmp_path).rstrip("\n").split("\n")
    header_i = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    lines = [ln + (",extra" if i == header_i else ",junk") if i >= header_i else ln
             for i, ln in enumerate(lines)]
    for _ in range(data.draw(st.integers(1, 4))):
        lines.insert(data.draw(st.integers(0, len(lines))), data.draw(st.sampled_from(["# note", "", "  "])))
    got = read_recording(_write(tmp_path, "\n".join(lines), "same.csv"))
    ref = read_recording(tmp_path / "v.csv")
    np.testing.assert_array_equal(got.t_s, ref.t_s)
    np.testing.assert_array_equal(got.b_T, ref.b_T)
    np.testing.assert_array_equal(got.m_Nm, ref.m_Nm)
    assert (got.w_ref_radps is None) == (ref.w_ref_radps is None)
    if ref.w_ref_radps is not None:
        np.testing.assert_array_equal(got.w_ref_radps, ref.w_ref_radps)
