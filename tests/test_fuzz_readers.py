"""Property-based fuzz of every reader: recording and rate-estimate CSVs, tlogs, TOML scenarios, key
files, uplink bytes (the flight software's) and downlink bytes (the ground decoder's).

Inputs are valid files or streams, then damaged the ways files and links get damaged: bits flipped,
bytes cut, inserted or repeated, lines and records swapped or repeated, cells replaced with huge, NaN,
infinite or non-numeric values, non-UTF-8 bytes, BOMs, CRLF, duplicate columns, deep nesting. The
properties: a reader returns a value that obeys its format's rules or raises its own error, naming the
file — never another exception, never a silently dropped row or record; a reader of a link never
raises, costs bounded work a tick, and never obeys a frame that is not genuinely signed.

Each property is two tests (`support.tiers`): the fast one (conftest.py's profile) and ``*_fuzz``,
marked slow, with 10,000 examples. Run the slow tier with ``pytest -m slow tests/test_fuzz_readers.py``.
"""
from __future__ import annotations

import copy
import datetime as dt
import math
import os
import stat
import struct
import tomllib
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from hypothesis import strategies as st
from pymavlink.generator.mavcrc import x25crc
from support import tiers

from fsw.commands import CommandRouter
from fsw.telemetry.dialect import FSW_COMPID, FSW_SYSID, GCS_SYSID, mavlink
from fsw.telemetry.framing import MESSAGES, Deframer, crc_x25
from fsw.telemetry.signing import (
    KEY_FILE_MAX_BYTES,
    KeyFileError,
    SigningClock,
    load_key,
    setup_outgoing,
    sign_ready,
    unix_to_timestamp,
)
from fsw.telemetry.uplink import Uplink
from ground.command import GroundLink
from ground.decode import Decoder
from ground.recording import RecordingError, read_rate_estimates, read_recording, write_rate_estimates, write_recording
from ground.tlog import TlogError, read_tlog
from hil import scenario as scenarios


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


# --- damage, the same for every kind of file --------------------------------------------------------

#: text that breaks numbers, lines, cells, encodings
HOSTILE_TOKENS = [b"nan", b"NaN", b"-nan", b"inf", b"-inf", b"Infinity", b"1e308", b"-1e308", b"1e309", b"1e-400",
                  b"0", b"-0", b"1_000", b"0x1F", b"1.2.3", b"--1", b"+", b".", b"e5", b" ", b"", b",", b",,",
                  b'"', b'"1,2"', b"#", b"\n", b"\r", b"\r\n", b"\x00", b"\t", b"\xef\xbb\xbf", b"\xff", b"\xfe\xff",
                  b"\xc3", b"\xed\xa0\x80", "\u0663".encode(), "é".encode(), "\u2028".encode(),
                  b"9" * 400, b"1" + b"0" * 330, b"=", b"[", b"]", b"{", b"}", b"'", b"\\"]


@st.composite
def damage(draw, data: bytes, max_ops: int = 4) -> bytes:
    """`data` with 1..max_ops byte-level injuries: a flipped byte, a cut, an insertion (random bytes, a
    hostile token or a copy of another part), a truncation, a swapped, repeated or lost line."""
    d = bytearray(data)
    for _ in range(draw(st.integers(1, max_ops))):
        op = draw(st.sampled_from(["flip", "cut", "insert", "token", "copy", "truncate", "swap_lines",
                                   "dup_line", "drop_line"]))
        pos = draw(st.integers(0, len(d)))
        if op == "flip" and d:
            d[min(pos, len(d) - 1)] ^= draw(st.integers(1, 255))
        elif op == "cut":
            del d[pos:pos + draw(st.integers(1, 64))]
        elif op == "insert":
            d[pos:pos] = draw(st.binary(min_size=1, max_size=32))
        elif op == "token":
            d[pos:pos] = draw(st.sampled_from(HOSTILE_TOKENS))
        elif op == "copy" and d:
            a = draw(st.integers(0, len(d) - 1))
            d[pos:pos] = d[a:a + draw(st.integers(1, 128))]
        elif op == "truncate":
            del d[pos:]
        elif op in ("swap_lines", "dup_line", "drop_line"):
            lines = bytes(d).split(b"\n")
            i, j = draw(st.integers(0, len(lines) - 1)), draw(st.integers(0, len(lines) - 1))
            if op == "swap_lines":
                lines[i], lines[j] = lines[j], lines[i]
            elif op == "dup_line":
                lines.insert(j, lines[i])
            else:
                del lines[i]
            d = bytearray(b"\n".join(lines))
    return bytes(d)


# --- recording and rate-estimate CSVs ---------------------------------------------------------------

T, B, M, W = ("t_s",), ("bx_uT", "by_uT", "bz_uT"), ("mx_Nm", "my_Nm", "mz_Nm"), ("wx_dps", "wy_dps", "wz_dps")
S = ("sx_dps", "sy_dps", "sz_dps")
finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)


def _cell(x: float) -> str:
    return "nan" if math.isnan(x) else "inf" if x == math.inf else repr(x)


#: values that are legal and awkward: zeros, the smallest subnormal, the largest floats, long decimals
ODD_VALUES = [0.0, -0.0, 5e-324, -5e-324, 2.2250738585072014e-308, 1.7976931348623157e308, -1.7976931348623157e308,
              0.1, 1 / 3, 123456789.12345679, 1e-300]


@st.composite
def csv_files(draw, kind: str):
    """A valid file of `kind` ("recording" or "rates"), in a random column order, maybe with an extra
    column and metadata: (text, {column: values}). The values come from a seeded generator (cheap to
    draw, reproducible), with a few legal but awkward values put in by hypothesis."""
    n = draw(st.integers(0, 12))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    scale = draw(st.sampled_from([1e-9, 1e-3, 1.0, 1e3, 1e6]))
    t0 = float(rng.normal(0, 1e6)) if draw(st.booleans()) else 0.0
    t = t0 + np.cumsum(rng.exponential(scale, n) + 1e-3 * (1 + abs(t0)) * 1e-6)
    cols: dict[str, list[float]] = {"t_s": [float(x) for x in t]}
    groups = [B] if kind == "recording" else [W, S]
    if kind == "recording":
        groups += [g for g in (M, W) if draw(st.booleans())]
    nan_share = draw(st.sampled_from([0.0, 0.2, 1.0]))
    for g in groups:
        for c in g:
            x = rng.normal(0, scale, n)
            if g == S:
                x = np.abs(x)
                x[rng.random(n) < nan_share / 2] = math.inf
            if g != B:
                x[rng.random(n) < nan_share / 2] = math.nan
            cols[c] = [float(v) for v in x]
    if n:
        for _ in range(draw(st.integers(0, 2))):
            c = draw(st.sampled_from([c for g in groups for c in g]))
            v = draw(st.sampled_from(ODD_VALUES))
            cols[c][draw(st.integers(0, n - 1))] = abs(v) if c in S else v
    names = list(cols)
    if draw(st.booleans()):
        names.append("note")
    order = list(rng.permutation(names))
    lines = [f"# {k}: {v}" for k, v in (("source", "fuzz"), ("licence", "x: y, z"))[:draw(st.integers(0, 2))]]
    lines.append(",".join(order))
    for i in range(n):
        lines.append(",".join("text" if c == "note" else _cell(cols[c][i]) for c in order))
    return "\n".join(lines) + "\n", cols


@st.composite
def harmless(draw, text: str) -> str:
    """The same data differently written: a BOM, CRLF, comment and blank lines, padded cells."""
    lines = text.rstrip("\n").split("\n")
    for _ in range(draw(st.integers(0, 3))):
        lines.insert(draw(st.integers(0, len(lines))), draw(st.sampled_from(["# note", "#", "", "   ", "\t"])))
    if draw(st.booleans()):
        lines = [",".join(f" {c} " for c in ln.split(",")) if ln and not ln.startswith("#") else ln
                 for ln in lines]
    text = ("\r\n" if draw(st.booleans()) else "\n").join(lines) + draw(st.sampled_from(["", "\n", "\r\n"]))
    return ("\ufeff" if draw(st.booleans()) else "") + text


def data_lines(text: str) -> int:
    """Rows the format says the text holds: non-comment, non-blank lines after the header."""
    lines = [ln.removesuffix("\r") for ln in text.split("\n")]
    return max(0, sum(1 for ln in lines if ln.strip() and not ln.startswith("#")) - 1)


def check_csv_read(path: Path, raw: bytes, kind: str):
    """Read `path` with the reader of `kind`: the value obeys the format, or RecordingError names the
    file. Returns the value (None when refused)."""
    reader = read_recording if kind == "recording" else read_rate_estimates
    try:
        got = reader(path)
    except RecordingError as e:
        assert e.path == str(path) and str(e).startswith(str(path)), e
        return None
    n = len(got)
    assert got.t_s.shape == (n,) and np.all(np.isfinite(got.t_s)) and np.all(np.diff(got.t_s) > 0)
    if kind == "recording":
        assert got.b_T.shape == (n, 3) and np.all(np.isfinite(got.b_T))
        assert got.m_Nm.shape == (n, 3) and not np.isinf(got.m_Nm).any()
        assert got.w_ref_radps is None or (got.w_ref_radps.shape == (n, 3) and not np.isinf(got.w_ref_radps).any())
    else:
        assert got.w_radps.shape == (n, 3) and not np.isinf(got.w_radps).any()
        s = got.sigma_radps
        assert s.shape == (n, 3) and not (s < 0).any() and not (s == -np.inf).any()
    assert n == data_lines(raw.decode("utf-8-sig")), "a row was dropped or invented"
    return got


def same_values(got, cols: dict, kind: str) -> None:
    np.testing.assert_array_equal(got.t_s, cols["t_s"])
    if kind == "recording":
        np.testing.assert_array_equal(got.b_T, np.array([cols[c] for c in B]).T.reshape(-1, 3) * 1e-6)
        if M[0] in cols:
            np.testing.assert_array_equal(got.m_Nm, np.array([cols[c] for c in M]).T.reshape(-1, 3))
        assert (got.w_ref_radps is None) == (W[0] not in cols)
        if W[0] in cols:
            np.testing.assert_array_equal(got.w_ref_radps, np.deg2rad(np.array([cols[c] for c in W]).T.reshape(-1, 3)))
    else:
        np.testing.assert_array_equal(got.w_radps, np.deg2rad(np.array([cols[c] for c in W]).T.reshape(-1, 3)))
        np.testing.assert_array_equal(got.sigma_radps, np.deg2rad(np.array([cols[c] for c in S]).T.reshape(-1, 3)))


#: (cell text, column kind) pairs the format refuses: in a required column anything not a finite number
BAD_REQUIRED = ["", " ", "nan", "NaN", "inf", "-inf", "1e309", "-1e999", "1_000", "0x1F", "1.2.3", "--1", "+",
                "abc", "\u0663", "1e", "e5", "1" + "0" * 400]


@st.composite
def csv_cases(draw, kind: str):
    """(bytes, original columns, what was done): harmless rewriting, damage, or one refused cell."""
    text, cols = draw(csv_files(kind))
    how = draw(st.sampled_from(["harmless", "damage", "bad_cell", "time_back", "duplicate_column"]))
    if how == "harmless":
        return draw(harmless(text)).encode(), cols, how
    if how == "damage":
        return draw(damage(draw(harmless(text)).encode())), cols, how
    lines = text.rstrip("\n").split("\n")
    h = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    names = lines[h].split(",")
    n = len(lines) - h - 1
    if how == "duplicate_column":
        lines[h] += "," + draw(st.sampled_from([c for c in names if c != "note"]))
        lines[h + 1:] = [ln + ",0" for ln in lines[h + 1:]]
    elif n == 0:
        return text.encode(), cols, "harmless"
    elif how == "bad_cell":
        required = ["t_s", *B] if kind == "recording" else ["t_s"]
        row, col = draw(st.integers(0, n - 1)), names.index(draw(st.sampled_from(required)))
        cells = lines[h + 1 + row].split(",")
        cells[col] = draw(st.sampled_from(BAD_REQUIRED))
        lines[h + 1 + row] = ",".join(cells)
    else:  # a later row's time not after an earlier one's
        if n < 2:
            return text.encode(), cols, "harmless"
        i = draw(st.integers(1, n - 1))
        j = draw(st.integers(0, i - 1))
        col = names.index("t_s")
        cells = lines[h + 1 + i].split(",")
        cells[col] = lines[h + 1 + j].split(",")[col]
        lines[h + 1 + i] = ",".join(cells)
    return ("\n".join(lines) + "\n").encode(), cols, how


def csv_property(kind: str):
    reader, writer = (read_recording, write_recording) if kind == "recording" else \
        (read_rate_estimates, write_rate_estimates)

    def prop(workdir, case):
        raw, cols, how = case
        path, out = workdir / f"{kind}.csv", workdir / f"{kind}-out.csv"
        path.write_bytes(raw)
        got = check_csv_read(path, raw, kind)
        if how == "harmless":
            assert got is not None, "a valid file was refused"
            same_values(got, cols, kind)
        elif how in ("bad_cell", "time_back", "duplicate_column"):
            assert got is None, f"{how}: accepted"
        assert path.read_bytes() == raw
        if got is not None:  # what the reader accepts, the writer writes and the reader reads back the same
            writer(out, got)
            back = reader(out)
            for name in ("t_s", "b_T", "m_Nm", "w_ref_radps", "w_radps", "sigma_radps"):
                a, b = getattr(got, name, None), getattr(back, name, None)
                assert (a is None) == (b is None), name
                if a is not None:
                    np.testing.assert_allclose(b, a, rtol=1e-14, atol=0, err_msg=name)

    prop.__name__ = f"{kind}_csv_property"
    return prop


test_recording_csv, test_recording_csv_fuzz = tiers(csv_property("recording"), case=csv_cases("recording"))
test_rate_csv, test_rate_csv_fuzz = tiers(csv_property("rates"), case=csv_cases("rates"))


# --- tlogs ------------------------------------------------------------------------------------------

KEY = bytes(range(7, 39))
WALL0_US = 1_750_000_000 * 1_000_000
#: the telemetry the box sends, and a few others
TLOG_IDS = sorted({mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, mavlink.MAVLINK_MSG_ID_HEARTBEAT,
                   mavlink.MAVLINK_MSG_ID_COMMAND_ACK, mavlink.MAVLINK_MSG_ID_PARAM_VALUE,
                   *(i for i in MESSAGES if 54000 <= i < 55000)})


def raw_frame(msgid: int, payload: bytes, seq: int = 0, sysid: int = FSW_SYSID, compid: int = FSW_COMPID,
              key: bytes | None = None, timestamp: int = 0) -> bytes:
    """A MAVLink 2 frame built by hand (not by pymavlink) around any payload of the right length for
    the message: its CRC correct, signed with `key` when given."""
    from fsw.telemetry.signing import signature
    head = bytes([0xFD, len(payload), 1 if key else 0, 0, seq & 0xFF, sysid, compid]) + msgid.to_bytes(3, "little")
    crc = crc_x25(head[1:] + payload, MESSAGES[msgid][0])
    frame = head + payload + struct.pack("<H", crc)
    if key:
        frame += bytes([0]) + timestamp.to_bytes(6, "little")
        frame += signature(key, frame)
    return frame


def random_frame(rng: np.random.Generator, ids=TLOG_IDS, key: bytes | None = None, timestamp: int = 0) -> bytes:
    """A frame of one of `ids` with random payload bytes (any field value: NaN, huge, any enum), at a
    length the message can have (senders truncate trailing zeros, never below 1 byte)."""
    msgid = int(rng.choice(ids))
    full = MESSAGES[msgid][2]
    n = int(rng.integers(1, full + 1)) if rng.random() < 0.3 else full
    payload = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
    return raw_frame(msgid, payload, int(rng.integers(256)), key=key, timestamp=timestamp)


@st.composite
def tlog_cases(draw):
    """(file bytes, the original records as (time stamp, frame), indices of those left intact). Records
    are swapped, repeated, dropped or moved in time; then the bytes are damaged. An original record is
    intact when none of its bytes was changed, cut or split by an insertion."""
    n = draw(st.integers(1, 20))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    signed = draw(st.booleans())
    t = WALL0_US + np.cumsum(rng.integers(0, 2_000_000, n)) & ~3
    records = [(int(t[k]), random_frame(rng, key=KEY if signed else None, timestamp=int(t[k] // 10)))
               for k in range(n)]
    order: list[tuple[int, int]] = [(k, int(t[k])) for k in range(n)]  # (original index or -1, stamp)
    touched: set[int] = set()
    for _ in range(draw(st.integers(0, 3))):
        op = draw(st.sampled_from(["swap", "repeat", "drop", "jump"]))
        i, j = draw(st.integers(0, len(order) - 1)), draw(st.integers(0, len(order) - 1))
        if op == "swap":
            order[i], order[j] = order[j], order[i]
        elif op == "repeat":
            order.insert(j, (-1 - order[i][0] if order[i][0] >= 0 else order[i][0], order[i][1]))
        elif op == "drop" and len(order) > 1:
            touched.add(order.pop(i)[0])
        elif op == "jump":  # a damaged time stamp: days off, still a plausible date
            k, stamp = order[i]
            days = draw(st.sampled_from([-400.0, -30.0, -3.5, -1.0, 1.0, 3.5, 30.0, 400.0]))
            order[i] = (k, (stamp + int(days * 86400e6)) & ~3)
            touched.add(k)
    data, owner = bytearray(), []
    for k, stamp in order:
        base = k if k >= 0 else -1 - k
        rec = struct.pack(">Q", stamp) + records[base][1]
        data += rec
        owner += [k if k >= 0 else -1] * len(rec)  # a repeated copy belongs to no original
    for _ in range(draw(st.integers(0, 3))):
        op = draw(st.sampled_from(["flip", "cut", "insert", "copy", "truncate"]))
        pos = draw(st.integers(0, len(data)))
        inside = 0 < pos < len(data) and owner[pos - 1] == owner[pos]
        if op == "flip" and data:
            pos = min(pos, len(data) - 1)
            data[pos] ^= draw(st.integers(1, 255))
            touched.add(owner[pos])
        elif op in ("cut", "truncate"):
            stop = len(data) if op == "truncate" else pos + draw(st.integers(1, 64))
            touched.update(owner[pos:stop])
            del data[pos:stop]
            del owner[pos:stop]
        elif op in ("insert", "copy"):
            if op == "insert":
                new = draw(st.binary(min_size=1, max_size=40)
                           | st.sampled_from([b"\xfd", b"\xfd\x09\x00", b"\x00" * 8]))
            else:
                a = draw(st.integers(0, max(len(data) - 1, 0)))
                new = bytes(data[a:a + draw(st.integers(1, 120))]) or b"\x00"
            if inside:
                touched.add(owner[pos])
            data[pos:pos] = new
            owner[pos:pos] = [-1] * len(new)
    intact = [k for k in range(n) if k not in touched and k in owner]
    return bytes(data), records, intact


def tlog_property(workdir, case):
    data, records, intact = case
    path = workdir / "f.tlog"
    path.write_bytes(data)
    reader = read_tlog(path)
    kept = []
    try:
        for r in reader:
            kept.append(r)
            assert r.messages and all(m.get_type() for m in r.messages)
    except TlogError as e:
        assert str(e).startswith(str(path)), e
        assert not intact, f"refused, but records {intact} are intact"
        return
    rep = reader.report
    assert rep.records == len(kept) and 0 <= rep.noise_records <= rep.records
    # every byte is in a kept record or counted as skipped
    assert sum(8 + len(r.data) for r in kept) + rep.skipped_bytes == len(data)
    assert [r.offset for r in kept] == sorted(r.offset for r in kept)
    got = Counter((r.t_us, r.data) for r in kept)
    want = Counter((records[k][0] & ~3, records[k][1]) for k in intact)
    lost = want - got
    assert not lost, f"intact records not recovered: {sorted(t for t, _ in lost)}; {rep.text()}"
    assert rep.damaged == bool(rep.skipped_bytes or rep.time_back or getattr(rep, "time_jumps", 0))
    assert path.read_bytes() == data


test_tlog, test_tlog_fuzz = tiers(tlog_property, case=tlog_cases())


# --- TOML scenarios ---------------------------------------------------------------------------------

SHIPPED = {name: tomllib.loads(scenarios.resolve(name).read_text(encoding="utf-8"))
           for name in scenarios.scenario_names()}
#: the tables every scenario needs, each with every key (hil/scenario.py's docstring)
REQUIRED_TABLES = ("body", "initial", "orbit", "field", "sensor")
#: keys of the required tables that may be left out (defaults, or optional parts of hil.scenario)
OPTIONAL_LEAVES = {("orbit", "box_tle"), ("field", "model"), ("field", "degree")}


class Raw:
    """A value written as the given TOML text: what the writer cannot make from Python values (an array
    nested thousands deep, an integer of thousands of digits)."""

    def __init__(self, text: str) -> None:
        self.text = text


def deep(depth: int) -> Raw:
    return Raw("[" * depth + "1" + "]" * depth)


def toml_value(v) -> str:
    if isinstance(v, Raw):
        return v.text
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, str):
        return '"' + "".join("\\" + c if c in '"\\' else f"\\u{ord(c):04x}" if ord(c) < 0x20 or ord(c) == 0x7F
                             else c for c in v) + '"'
    if isinstance(v, (dt.datetime, dt.date, dt.time)):
        return v.isoformat()
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(type(v))


def toml_text(doc: dict) -> str:
    """TOML for the subset scenarios use: top-level values, tables, arrays of tables."""
    lines = []
    for k, v in doc.items():
        if not isinstance(v, dict) and not (isinstance(v, list) and v and all(isinstance(x, dict) for x in v)):
            lines.append(f"{k} = {toml_value(v)}")
    for k, v in doc.items():
        if isinstance(v, dict):
            lines += ["", f"[{k}]", *(f"{kk} = {toml_value(x)}" for kk, x in v.items())]
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            for item in v:
                lines += ["", f"[[{k}]]", *(f"{kk} = {toml_value(x)}" for kk, x in item.items())]
    return "\n".join(lines) + "\n"


#: values no number in a scenario may take: not a finite number that a float holds
NOT_A_NUMBER = [math.nan, math.inf, -math.inf, 10**400, -(10**400), "10", "", True, False, dt.date(2025, 1, 1),
                dt.datetime(2025, 1, 1, 12, 0), dt.time(12, 0), {}, {"x": 1.0}, deep(3), Raw("9" * 5000),
                Raw("1e400"), Raw("-0x7fffffffffffffffff")]
#: numbers that may or may not be allowed where they land
ODD_NUMBERS = [0, 0.0, -0.0, -1, -1.0, 1e308, -1e308, 5e-324, 2**63, -(2**63), 2**64, 1e-300, 999.9, 1000.0, 1000.1,
               100, 200, 400, 800, 99.9, 50_000.0, 50_000.1]


def _leaves(doc: dict):
    """(path, value) of every value in a scenario document; a path is a tuple of keys and indices."""
    for k, v in doc.items():
        if isinstance(v, dict):
            for kk, x in v.items():
                yield (k, kk), x
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            for i, item in enumerate(v):
                for kk, x in item.items():
                    yield (k, i, kk), x
        else:
            yield (k,), v


def _get(doc, path):
    for p in path[:-1]:
        doc = doc[p]
    return doc, path[-1]


@st.composite
def scenario_cases(draw):
    """(file bytes, invalid): a shipped scenario changed the ways a hand-edited file goes wrong. `invalid`
    is True when a change certainly breaks the format (a number that is not one, a missing required
    key, an unknown key, a wrong shape), whatever else was done."""
    doc = copy.deepcopy(SHIPPED[draw(st.sampled_from(sorted(SHIPPED)))])
    invalid = False
    # changes that may or may not break it, then at most one that certainly does (so that no later
    # change can undo it)
    ops = draw(st.lists(st.sampled_from(["odd_number", "element", "torque", "deorbit", "inertia", "string"]),
                        max_size=2))
    first = len(ops)
    ops += draw(st.lists(st.sampled_from(["not_a_number", "element", "shape", "delete", "unknown", "table_type",
                                          "torque", "deep", "string"]), max_size=1))
    for i, op in enumerate(ops):
        may_break = i >= first
        leaves = list(_leaves(doc))
        numeric = [(p, v) for p, v in leaves if isinstance(v, (int, float, list)) and not isinstance(v, bool)]
        if op in ("not_a_number", "odd_number") and numeric:
            p, v = draw(st.sampled_from(numeric))
            new = draw(st.sampled_from(NOT_A_NUMBER if op == "not_a_number" else ODD_NUMBERS))
            parent, key = _get(doc, p)
            parent[key] = new
            invalid |= op == "not_a_number"
        elif op == "element":
            arrays = [(p, v) for p, v in numeric if isinstance(v, list) and v]
            if arrays:
                p, v = draw(st.sampled_from(arrays))
                flat = v if not isinstance(v[0], list) else v[draw(st.integers(0, len(v) - 1))]
                bad = may_break and draw(st.booleans())
                flat[draw(st.integers(0, len(flat) - 1))] = draw(st.sampled_from(NOT_A_NUMBER if bad else ODD_NUMBERS))
                invalid |= bad
        elif op == "shape":
            arrays = [(p, v) for p, v in numeric if isinstance(v, list) and v]
            if arrays:
                p, v = draw(st.sampled_from(arrays))
                parent, key = _get(doc, p)
                parent[key] = draw(st.sampled_from([[], v[:-1], v + v[-1:], [v], 1.0]))
                invalid = True
        elif op == "delete":
            p, _ = draw(st.sampled_from(leaves))
            parent, key = _get(doc, p)
            del parent[key]
            invalid |= (p[0] in REQUIRED_TABLES and tuple(p[:2]) not in OPTIONAL_LEAVES) or p[0] == "torque"
        elif op == "unknown":
            where = draw(st.sampled_from([None, *(k for k, v in doc.items() if isinstance(v, dict))]))
            (doc if where is None else doc[where])[draw(st.sampled_from(["extra", "mass_kg_", "Name", "x"]))] = 1.0
            invalid = True
        elif op == "table_type":
            table = draw(st.sampled_from(REQUIRED_TABLES))
            doc[table] = draw(st.sampled_from([1.0, "body", [1.0], [doc.get(table, {})]]))
            invalid = True
        elif op == "torque":
            pulse = {"start_s": draw(st.sampled_from([0.0, 1.0, -1.0, 1e308])),
                     "duration_s": draw(st.sampled_from([1.0, 0.0, -1.0, 1e308])),
                     "moment_Nm": draw(st.sampled_from([[0.1, 0.0, 0.0], [1e308, -1e308, 0.0], [0.0, 0.0]]))}
            if may_break and draw(st.booleans()):
                bad_key = draw(st.sampled_from(list(pulse)))
                pulse[bad_key] = draw(st.sampled_from(NOT_A_NUMBER))
                invalid = True
            doc.setdefault("torque", [])
            if isinstance(doc["torque"], list):
                doc["torque"].append(pulse)
        elif op == "deorbit":
            d = doc.setdefault("deorbit", {})
            if isinstance(d, dict):
                key = draw(st.sampled_from(["sail_area_m2", "duration_s", "settle_s", "density_kgm3", "cp_offset_m",
                                            "initial_ypr_deg", "dipole_Am2"]))
                d[key] = draw(st.sampled_from(NOT_A_NUMBER + ODD_NUMBERS + [[0.0, 0.0, 0.0], [1.0, 2.0]]))
        elif op == "inertia" and isinstance(doc.get("body"), dict):
            doc["body"]["inertia_kgm2"] = draw(st.sampled_from([
                [[1, 0, 0], [0, 1, 0], [0, 0, 3]], [[1, 0.5, 0], [0, 1, 0], [0, 0, 1]],
                [[-1, 0, 0], [0, 1, 0], [0, 0, 1]],
                [[0, 0, 0], [0, 0, 0], [0, 0, 0]], [[1e308, 0, 0], [0, 1e308, 0], [0, 0, 1e308]],
                [[1e-300, 0, 0], [0, 1e-300, 0], [0, 0, 1e-300]], [[2, 1, 1], [1, 2, 1], [1, 1, 2]]]))
        elif op == "deep":
            table = draw(st.sampled_from(REQUIRED_TABLES))
            if isinstance(doc.get(table), dict):
                doc[table][draw(st.sampled_from(list(doc[table]) or ["x"]))] = deep(draw(st.sampled_from([50, 5000])))
                invalid = True
        elif op == "string":
            key = draw(st.sampled_from(["name", "description", "source"]))
            doc[key] = draw(st.sampled_from(["", "é\u2028x", "\x00\x1f\x7f", "a" * 10_000]
                                            + ([1.0, [], True] if may_break else [])))
            invalid |= not isinstance(doc[key], str)
    text = toml_text(doc).encode()
    if draw(st.integers(0, 3)) == 0:  # and damage to the text itself
        return draw(damage(text, max_ops=2)), False
    return text, invalid


def check_scenario(scn: scenarios.Scenario) -> None:
    """The values a loaded scenario holds obey what hil/scenario.py promises."""
    def finite(a) -> bool:
        return bool(np.all(np.isfinite(np.asarray(a, dtype=float))))

    J = scn.inertia_kgm2
    assert J.shape == (3, 3) and finite(J) and np.allclose(J, J.T, rtol=0, atol=1e-12 * np.abs(J).max())
    assert np.linalg.eigvalsh(J)[0] > 0
    assert math.isfinite(scn.mass_kg) and scn.mass_kg > 0
    for a in (scn.omega0_radps, scn.attitude_rpy_deg, scn.bridge_offset_T):
        assert a.shape == (3,) and finite(a)
    assert 100e3 <= scn.altitude_m <= 50_000e3
    assert all(math.isfinite(x) for x in (scn.inclination_deg, scn.raan_deg, scn.arg_lat0_deg, scn.epoch_year))
    assert 0 < scn.sample_rate_hz <= 1000 and scn.bandwidth_hz in (100, 200, 400, 800)
    assert math.isfinite(scn.noise_T) and scn.noise_T >= 0
    for p in scn.torques:
        assert p.start_s >= 0 and p.duration_s > 0 and finite([p.start_s, p.duration_s]) and finite(p.moment_Nm)
    if scn.deorbit is not None:
        d = scn.deorbit
        for k in ("sail_area_m2", "drag_coefficient", "density_kgm3", "density_scale_height_km", "dipole_Am2",
                  "duration_s"):
            assert math.isfinite(getattr(d, k)) and getattr(d, k) > 0
        assert 0 <= d.settle_s < d.duration_s
    assert isinstance(scn.name, str) and isinstance(scn.description, str)


def scenario_property(workdir, case):
    text, invalid = case
    path = workdir / "s.toml"
    path.write_bytes(text)
    try:
        scn = scenarios.load(str(path))
    except scenarios.ScenarioError as e:
        assert str(path) in str(e), e
        return
    assert not invalid, "an invalid scenario was accepted"
    check_scenario(scn)
    assert path.read_bytes() == text


test_scenario, test_scenario_fuzz = tiers(scenario_property, case=scenario_cases())


def test_every_shipped_scenario_written_back_loads_the_same(tmp_path):
    """The TOML writer of the fuzz writes what the files say (else the fuzz tests nothing)."""
    for name, doc in SHIPPED.items():
        path = tmp_path / f"{name}.toml"
        path.write_text(toml_text(doc))
        a, b = scenarios.load(name), scenarios.load(str(path))
        np.testing.assert_array_equal(a.inertia_kgm2, b.inertia_kgm2)
        assert (a.mass_kg, a.sample_rate_hz, len(a.torques), a.deorbit) == \
            (b.mass_kg, b.sample_rate_hz, len(b.torques), b.deorbit)


# --- key files --------------------------------------------------------------------------------------

KEY_HEX = KEY.hex()


@st.composite
def key_file_cases(draw):
    """(kind of file, mode, content): a key file as written, as a person might edit it, damaged, too
    long, a placeholder; a regular file, a symbolic link to one, a directory, a FIFO, nothing."""
    key_hex = draw(st.sampled_from([KEY_HEX, KEY_HEX.upper(), "00" * 32, "ab" * 32, KEY_HEX[:62], KEY_HEX + "00"]))
    content = (draw(st.sampled_from(["", " ", "\t", "\ufeff", "0x"])) + key_hex
               + draw(st.sampled_from(["\n", "", "\r\n", "\n\n", "  \n", " x\n"]))).encode()
    how = draw(st.sampled_from(["as is", "damage", "long", "spaced"]))
    if how == "damage":
        content = draw(damage(content, max_ops=2))
    elif how == "long":
        content += draw(st.sampled_from([b" ", b"\n", b"0", b"#"])) * draw(st.sampled_from(
            [KEY_FILE_MAX_BYTES - len(content), KEY_FILE_MAX_BYTES - len(content) + 1, 10_000]))
    elif how == "spaced":  # hex digits in pairs, the pairs apart
        content = " ".join(key_hex[i:i + 2] for i in range(0, len(key_hex), 2)).encode() + b"\n"
    kind = draw(st.sampled_from(["file", "file", "file", "symlink", "dir", "fifo", "missing", "dangling"]))
    mode = draw(st.sampled_from([0o600, 0o600, 0o400, 0o644, 0o640, 0o604, 0o700, 0o000]))
    return kind, mode, content


def key_file_property(workdir, case):
    kind, mode, content = case
    d = workdir / "keys"
    d.mkdir(exist_ok=True)
    path, target = d / "mission.key", d / "target.key"
    for p in (path, target):
        if p.is_dir() and not p.is_symlink():
            p.rmdir()
        elif p.exists() or p.is_symlink():
            p.unlink()
    if kind in ("file", "symlink"):
        real = path if kind == "file" else target
        real.write_bytes(content)
        real.chmod(mode)
        if kind == "symlink":
            path.symlink_to(target)
    elif kind == "dir":
        path.mkdir()
    elif kind == "fifo":
        os.mkfifo(path)
    elif kind == "dangling":
        path.symlink_to(d / "nowhere")
    try:
        key = load_key(path)
    except KeyFileError as e:
        assert str(path) in str(e), e
        canonical = kind in ("file", "symlink") and content in (KEY_HEX.encode() + b"\n", KEY_HEX.encode())
        readable = os.geteuid() == 0 or mode & 0o400
        assert not (canonical and mode in (0o600, 0o400) and readable), f"a valid key file was refused: {e}"
        return
    # accepted: a private regular file, not too long, holding exactly the key's hex digits
    assert kind in ("file", "symlink")
    st_ = os.stat(path)
    assert stat.S_ISREG(st_.st_mode) and not st_.st_mode & 0o077
    assert len(content) <= KEY_FILE_MAX_BYTES
    assert len(key) == 32 and len(set(key)) > 1
    assert "".join(content.decode("ascii").split()).lower() == key.hex()


test_key_file, test_key_file_fuzz = tiers(key_file_property, case=key_file_cases())


# --- uplink bytes (the flight software's commands) --------------------------------------------------

OTHER_KEY = bytes(range(100, 132))
T0_TICKS = unix_to_timestamp(1_750_000_000.0)
TAG_CMD = mavlink.MAV_CMD_USER_1


def noise(rng: np.random.Generator, kind: str) -> bytes:
    n = int(rng.integers(1, 300))
    if kind == "random":
        return rng.integers(0, 256, n, dtype=np.uint8).tobytes()
    if kind == "stx flood":
        return bytes([0xFD]) * n
    # headers that pass every cheap check, then nothing right: the costly kind of flood
    return b"".join(bytes([0xFD, 33, 0, 0, 0, 255, 190, 76, 0, 0]) + rng.integers(0, 256, 4, dtype=np.uint8).tobytes()
                    for _ in range(n // 14 + 1))


def whole_frame_at(data: bytes, at: int) -> bool:
    """A MAVLink 2 frame starts at `at`, all of it there and its CRC right (checked with pymavlink's x25)."""
    if at + 10 > len(data) or data[at] != 0xFD:
        return False
    end = at + 12 + data[at + 1]
    msg = mavlink.mavlink_map.get(int.from_bytes(data[at + 7:at + 10], "little"))
    if msg is None or end + (13 if data[at + 2] & 1 else 0) > len(data):
        return False
    crc = x25crc(data[at + 1:end - 2])
    crc.accumulate([msg.crc_extra])
    return crc.crc == data[end - 2] | data[end - 1] << 8


@st.composite
def uplink_streams(draw):
    """(chunks of bytes in arrival order, tags of the genuine commands): genuine signed COMMAND_LONGs
    (param1 = a unique tag) among forged ones (another key, unsigned, to another system), replays,
    damaged copies (a flipped byte, a cut, the last bytes lost, two spliced) and noise; cut into
    chunks at random."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    now = [0.0]

    def link(key, sysid=GCS_SYSID):
        return GroundLink(lambda b: None, key, SigningClock(epoch=T0_TICKS), sysid=sysid)

    ground, forger, plain = link(KEY), link(OTHER_KEY), link(None)
    pieces, genuine, sent, ends = [], [], [], []
    for tag in range(draw(st.integers(1, 12))):
        now[0] += float(rng.uniform(0, 2))
        kind = draw(st.sampled_from(["genuine", "genuine", "other key", "unsigned", "not for us", "replay", "flip",
                                     "cut", "tail lost", "splice", "noise"]))
        if kind == "genuine":
            f = ground.command_long(TAG_CMD, [float(tag)], now[0])
            genuine.append(tag)
            sent.append(f)
        elif kind == "other key":
            f = forger.command_long(TAG_CMD, [float(tag)], now[0])
        elif kind == "unsigned":
            f = plain.command_long(TAG_CMD, [float(tag)], now[0])
        elif kind == "not for us":
            f = ground.command_long(TAG_CMD, [float(tag)], now[0], target=(FSW_SYSID + 1, FSW_COMPID))
        elif kind == "noise":
            f = noise(rng, draw(st.sampled_from(["random", "stx flood", "header flood"])))
        else:
            g = bytearray(ground.command_long(TAG_CMD, [float(tag)], now[0]))  # made, never sent whole
            if kind == "replay":
                f = sent[int(rng.integers(len(sent)))] if sent else b""
            elif kind == "flip":
                g[int(rng.integers(len(g)))] ^= int(rng.integers(1, 256))
                f = bytes(g)
            elif kind == "cut":
                a = int(rng.integers(len(g)))
                f = bytes(g[:a] + g[a + int(rng.integers(1, 20)):])
            elif kind == "tail lost":
                f = bytes(g[:-int(rng.integers(1, 14))])
            else:
                h = ground.command_long(TAG_CMD, [float(tag) + 0.5], now[0])
                f = bytes(g[:len(g) // 2]) + h[len(h) // 2:]
            if f and len(f) < len(g) and g.startswith(f):  # its end lost: what follows may be that very end
                ends.append((tag, sum(map(len, pieces)) + len(f), bytes(g[len(f):])))
        pieces.append(f)
    data = b"".join(pieces)
    cuts = sorted(set(draw(st.lists(st.integers(0, len(data)), max_size=8))) | {0, len(data)})
    # a frame whose lost end is what happens to follow it (the next frame's 0xFD when its signature's last
    # byte was 0xFD, noise) arrives whole: genuine after all — unless a whole frame (its CRC right) starts
    # there, inside the completed one's signature block, and has arrived by the time the completed one
    # has: by design the box then takes that next frame, not the one it would cut; when the next frame's
    # rest is still to come, the completed one is obeyed at once (fsw.telemetry.framing)
    completed = [(tag, at, at + len(lost)) for tag, at, lost in ends if data.startswith(lost, at)]
    genuine = sorted(genuine + [tag for tag, at, end in completed
                                if not whole_frame_at(data[:next(c for c in cuts if c >= end)], at)])
    authentic = sorted(set(genuine) | {tag for tag, _, _ in completed})  # whatever the chunks
    return [data[a:b] for a, b in zip(cuts, cuts[1:])], genuine, authentic


def make_uplink(key, **kw):
    router = CommandRouter()
    obeyed: list[float] = []
    router.register(TAG_CMD, lambda m, t: obeyed.append(m.param1))
    answers: list = []
    up = Uplink(None, router, sysid=FSW_SYSID, compid=FSW_COMPID, key=key,
                clock=SigningClock(epoch=T0_TICKS, clock_set=True), reply=answers.append, **kw)
    return up, obeyed, answers


def uplink_property(case):
    """Fed as a stream: never raises; with the key, exactly the genuine commands are obeyed, each once;
    without a key, none (a state-changing command needs a signature)."""
    chunks, genuine, _ = case
    for key in (KEY, None):
        up, obeyed, _ = make_uplink(key)
        for k, c in enumerate(chunks):
            up.feed(c, 0.01 * k)
        assert up.counters.parser_resets == 0
        assert up.counters.bytes == sum(map(len, chunks))
        if key is None:
            assert obeyed == []
        else:
            assert obeyed == [float(t) for t in genuine], (obeyed, genuine)


test_uplink, test_uplink_fuzz = tiers(uplink_property, case=uplink_streams())


class StreamLink:
    """A byte stream (a serial radio): recv(n) gives at most n bytes of what has arrived."""

    def __init__(self, data: bytes) -> None:
        self.data = bytearray(data)
        self.served = 0

    def recv(self, n: int) -> bytes:
        out = bytes(self.data[:n])
        del self.data[:n]
        self.served += len(out)
        return out


class DatagramLink:
    """A UDP socket: read_datagrams(n) gives at most n of the waiting datagrams (data, address, size)."""

    def __init__(self, datagrams: list[tuple[bytes, tuple]]) -> None:
        self.waiting = list(datagrams)
        self.served = 0

    def read_datagrams(self, n: int) -> list:
        out, self.waiting = self.waiting[:n], self.waiting[n:]
        self.served += len(out)
        return [(d, addr, len(d)) for d, addr in out]


BUDGETS = dict(max_bytes_per_tick=512, max_datagrams_per_tick=8, max_parsed_per_tick=4, max_crc_checks_per_tick=6,
               max_frames_per_tick=3)


def bounded_work_property(case):
    """Polled a tick at a time, on a stream link and on a datagram link: per tick at most the budgets'
    bytes read, datagrams taken, CRCs computed and frames decoded, whatever arrives; never raises;
    never obeys a frame that is not genuine; a genuine command arriving alone on a quiet datagram link
    is obeyed."""
    chunks, _, authentic = case
    data = b"".join(chunks)
    for conn in (StreamLink(data), DatagramLink([(c, ("10.0.0.9", 14550 + k % 3)) for k, c in enumerate(chunks)])):
        up, obeyed, _ = make_uplink(KEY, **BUDGETS)
        decoded: list = []

        def counting(frame, decoded=decoded, real=up._deframer.decode):
            decoded.append(frame)
            return real(frame)

        up._deframer.decode = counting
        for tick in range(2 + len(data) // 64):
            crc0, served0, n0 = up._deframer.crc_checks, conn.served, len(decoded)
            up.poll(0.02 * tick)
            assert up._deframer.crc_checks - crc0 <= BUDGETS["max_crc_checks_per_tick"]
            assert len(decoded) - n0 <= BUDGETS["max_frames_per_tick"]
            limit = BUDGETS["max_bytes_per_tick"] if isinstance(conn, StreamLink) else BUDGETS["max_datagrams_per_tick"]
            assert conn.served - served0 <= limit
        assert up.counters.parser_resets == 0
        assert set(obeyed) <= {float(t) for t in authentic} and len(obeyed) == len(set(obeyed))
    quiet = GroundLink(lambda b: None, KEY, SigningClock(epoch=T0_TICKS))
    up, obeyed, _ = make_uplink(KEY, **BUDGETS)
    up.conn = DatagramLink([(c, ("10.0.0.9", 14550)) for c in chunks] +
                           [(quiet.command_long(TAG_CMD, [99.0], 1000.0), ("10.0.0.1", 14550))])
    for tick in range(len(chunks) // BUDGETS["max_datagrams_per_tick"] + 2):
        up.poll(1000.0 + 0.02 * tick)
    assert 99.0 in obeyed


test_uplink_bounded_work, test_uplink_bounded_work_fuzz = tiers(bounded_work_property, case=uplink_streams())


# --- downlink bytes (the ground decoder) ------------------------------------------------------------

DOWNLINK_IDS = sorted({mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, *(i for i in MESSAGES if 54000 <= i < 55000),
                       mavlink.MAVLINK_MSG_ID_HEARTBEAT})


@st.composite
def downlink_streams(draw):
    """(chunks, key or None, times of the genuine magnetometer samples): a box's HIGHRES_IMU samples
    (strictly increasing times, finite field; signed when there is a key) among frames of every
    telemetry message with random payloads (any value: NaN, inf, huge times, any run id or method),
    from the box and from other systems, damaged copies and noise."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    key = draw(st.sampled_from([None, KEY]))
    p = mavlink.MAVLink(None, srcSystem=FSW_SYSID, srcComponent=FSW_COMPID)
    clock = SigningClock(epoch=T0_TICKS)
    if key is not None:
        setup_outgoing(p, key, clock)
    pieces, genuine = [], []
    t_us = int(rng.integers(0, 10**9))
    for _ in range(draw(st.integers(1, 30))):
        kind = draw(st.sampled_from(["sample", "sample", "random", "random other", "flip", "noise", "cut"]))
        if kind in ("sample", "flip", "cut"):
            t_us += int(rng.integers(1, 2_000_000))
            b = rng.normal(0, 0.5, 3)
            msg = mavlink.MAVLink_highres_imu_message(t_us, 0, 0, 0, 0, 0, 0, *b, 0, 0, 0, 0, 0x1C0)
            if key is not None:
                sign_ready(p, clock, 0.0)
            f = bytearray(msg.pack(p))
            p.seq = (p.seq + 1) % 256
            if kind == "flip":
                f[int(rng.integers(len(f)))] ^= int(rng.integers(1, 256))
            elif kind == "cut":
                f = f[:int(rng.integers(1, len(f)))]
            else:
                genuine.append(t_us)
            pieces.append(bytes(f))
        elif kind in ("random", "random other"):
            f = random_frame(rng, DOWNLINK_IDS)
            if kind == "random":  # as if from the box
                f = bytearray(f)
                f[5], f[6] = FSW_SYSID, FSW_COMPID
                f[-2:] = struct.pack("<H", crc_x25(bytes(f[1:-2]), MESSAGES[f[7] | f[8] << 8 | f[9] << 16][0]))
                f = bytes(f)
            pieces.append(f)
        else:
            pieces.append(noise(rng, draw(st.sampled_from(["random", "stx flood", "header flood"]))))
    data = b"".join(pieces)
    cuts = sorted(set(draw(st.lists(st.integers(0, len(data)), max_size=6))) | {0, len(data)})
    return [data[a:b] for a, b in zip(cuts, cuts[1:])], key, genuine


def downlink_property(workdir, case):
    """Never raises; every run's recording and rate estimates obey the formats and write; no
    magnetometer sample is invented and none of the box's intact ones is lost."""
    chunks, key, genuine = case
    dec = Decoder(key=key, method=mavlink.DEBRIS_RATE_METHOD_KALMAN)
    df = Deframer()
    now = 1_750_000_000.0
    for k, c in enumerate(chunks):
        for m in df.feed(c):
            dec.handle(m, now + 0.01 * k)
    for m in df.flush():
        dec.handle(m, now + 1.0)
    dec.finish()
    dec.summary_text()
    dec.status_line()
    recorded = set()
    for stream in dec.streams.values():
        for seg in stream.segments:
            rec, est = dec.recording(seg), dec.rate_estimates(seg)
            assert np.all(np.diff(rec.t_s) > 0) and np.all(np.isfinite(rec.b_T)), "recording breaks the format"
            write_recording(workdir / "rec.csv", rec)
            write_rate_estimates(workdir / "rates.csv", est)
            if stream.source == (FSW_SYSID, FSW_COMPID):
                recorded |= set(seg.times())
    assert set(genuine) <= recorded, f"samples lost: {sorted(set(genuine) - recorded)[:5]}"


test_downlink, test_downlink_fuzz = tiers(downlink_property, case=downlink_streams())
