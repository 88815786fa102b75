"""Magnetometer recordings and rate estimates as CSV: recording format v1 (docs/spec/recording-format.md).

One plain format for SITL output, telemetry exported by the ground station and public datasets, so
that every estimator reads the same thing. Units are converted only here, at the file edge: the file
holds µT and °/s (unit in the column name), the arrays in memory hold tesla, rad/s and N·m.

Recording columns: ``t_s`` (strictly increasing), ``bx_uT, by_uT, bz_uT`` (required);
``mx_Nm, my_Nm, mz_Nm`` (known applied moment, optional, zeros when the columns are absent) and
``wx_dps, wy_dps, wz_dps`` (reference rate for scoring, optional); ``kit_bx_uT, kit_by_uT, kit_bz_uT``
(the de-orbit kit's field at the sensor that the box took out of the sample, as modelled on board;
optional: the field columns stay the sensor's own) and ``flags`` (the sample's DEBRIS_SAMPLE_FLAGS
without RESENT, an integer: 2 = KIT_MOVING, taken while a shutter or magnet moved; optional).
Rate-estimate columns: ``t_s, wx_dps, wy_dps, wz_dps, sx_dps, sy_dps, sz_dps`` (NaN where no estimate
exists; a σ of ``inf`` where the estimator had no information: a degenerate sample, e.g. a zero field).

Reading rules (spec, "Rules"):
- a line starting with ``#`` is a comment; ``# key: value`` comments become metadata (a key given on
  several lines before the header is joined with newlines; after the header, where a writer appends what
  it learnt while recording, a key given again replaces its earlier value, consecutive lines of one key
  being one value);
- the first other non-blank line is the header; columns the format does not name are ignored;
- an empty, non-numeric, NaN or infinite cell in a required column, a non-increasing or non-finite
  time, a row with the wrong number of cells, or bytes that are not UTF-8 raise `RecordingError`
  naming the file, the 1-based line as in the file, and the column. No row is ever dropped.
- optional columns come in whole triads; in them a cell may be empty or ``nan`` (reference unknown
  for that sample, e.g. a truth frame lost on the link), never infinite or non-numeric.
- numbers are plain decimals (``-1.5``, ``2e-3``); Python-only spellings such as ``1_000`` are
  rejected rather than read as something the author did not mean.

Writing: time with the shortest text that reads back exactly, other values with 15 significant
digits (unit conversions leave noise in the 16th–17th). Atomic (`fsw.files.write_atomic`: a temporary
file in the same folder, then `os.replace`): on any error nothing is written and an existing file is
left as it was.
"""
from __future__ import annotations

import csv
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from fsw.files import write_atomic
from fsw.estimation import field_check

PathLike = str | os.PathLike

#: Column names of the recording format v1.
T_COLUMN = "t_s"
B_COLUMNS = ("bx_uT", "by_uT", "bz_uT")
M_COLUMNS = ("mx_Nm", "my_Nm", "mz_Nm")
W_COLUMNS = ("wx_dps", "wy_dps", "wz_dps")
#: Column names of the rate-estimate output.
SIGMA_COLUMNS = ("sx_dps", "sy_dps", "sz_dps")
#: The kit's field the box took out of each sample, and the sample's flags (optional columns).
KIT_COLUMNS = ("kit_bx_uT", "kit_by_uT", "kit_bz_uT")
FLAGS_COLUMN = "flags"

T_PER_UT = 1e-6

_NUMBER = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_COLUMN = re.compile(rf"(?:{_NUMBER.pattern}\n)*{_NUMBER.pattern}")
_COLUMN_NAN_OK = re.compile(rf"(?:(?:{_NUMBER.pattern}|nan|NaN|)\n)*(?:{_NUMBER.pattern}|nan|NaN|)")
_NAN_WORDS = frozenset({"nan", "+nan", "-nan"})
_INF_WORDS = frozenset({"inf", "+inf", "infinity", "+infinity"})
_META = re.compile(r"#\s*([A-Za-z_][A-Za-z0-9_.\-]*)\s*:\s?(.*)")


class RecordingError(ValueError):
    """A recording or rate-estimate file (or the data about to be written to one) breaks the format.

    `path`, `line` (1-based, as in the file; None for file-level problems) and `column` (column name,
    or None) say where.
    """

    def __init__(self, path: PathLike | None, line: int | None, column: str | None, reason: str):
        self.path = None if path is None else str(path)
        self.line = line
        self.column = column
        self.reason = reason
        where = self.path or "<recording>"
        if line is not None:
            where += f":{line}"
        if column is not None:
            where += f": column {column!r}"
        super().__init__(f"{where}: {reason}")


@dataclass
class Recording:
    """A magnetometer recording in SI units.

    t_s (N,) s, strictly increasing; b_T (N, 3) tesla in the sensor axes; m_Nm (N, 3) known applied
    moment about the centre of mass, N·m (zeros when the file has none; NaN rows = unknown);
    w_ref_radps (N, 3) reference body rate for scoring only, or None; metadata from ``# key: value``;
    kit_T (N, 3) the de-orbit kit's field at the sensor the box took out (b_T still includes it), or None;
    flags (N,) int, the samples' DEBRIS_SAMPLE_FLAGS (RESENT excluded), or None.
    """

    t_s: np.ndarray
    b_T: np.ndarray
    m_Nm: np.ndarray | None = None
    w_ref_radps: np.ndarray | None = None
    metadata: dict[str, str] = field(default_factory=dict)
    path: Path | None = None
    kit_T: np.ndarray | None = None
    flags: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.t_s = _vector(self.t_s, "t_s")
        n = self.t_s.shape[0]
        self.b_T = _triads(self.b_T, n, "b_T")
        self.m_Nm = np.zeros((n, 3)) if self.m_Nm is None else _triads(self.m_Nm, n, "m_Nm")
        if self.w_ref_radps is not None:
            self.w_ref_radps = _triads(self.w_ref_radps, n, "w_ref_radps")
        if self.kit_T is not None:
            self.kit_T = _triads(self.kit_T, n, "kit_T")
        if self.flags is not None:
            self.flags = np.asarray(self.flags, dtype=np.int64)
            if self.flags.shape != (n,):
                raise ValueError(f"flags must have shape ({n},), got {self.flags.shape}")
        self.metadata = dict(self.metadata)

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    def rows(self, index) -> Recording:
        """The recording of the rows `index` selects (a mask, indices or a slice), every column kept."""
        def pick(a):
            return None if a is None else a[index]
        return Recording(self.t_s[index], self.b_T[index], self.m_Nm[index], pick(self.w_ref_radps), self.metadata,
                         self.path, pick(self.kit_T), pick(self.flags))


@dataclass
class RateEstimates:
    """Body-rate estimates, one row per input sample: t_s (N,), w_radps and its 1-σ sigma_radps
    (N, 3), rad/s; NaN where no estimate exists yet."""

    t_s: np.ndarray
    w_radps: np.ndarray
    sigma_radps: np.ndarray
    metadata: dict[str, str] = field(default_factory=dict)
    path: Path | None = None

    def __post_init__(self) -> None:
        self.t_s = _vector(self.t_s, "t_s")
        n = self.t_s.shape[0]
        self.w_radps = _triads(self.w_radps, n, "w_radps")
        self.sigma_radps = _triads(self.sigma_radps, n, "sigma_radps")
        self.metadata = dict(self.metadata)

    def __len__(self) -> int:
        return int(self.t_s.shape[0])


def _vector(a, name: str) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    if a.ndim != 1:
        raise ValueError(f"{name} must have shape (N,), got {a.shape}")
    return a


def _triads(a, n: int, name: str) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    if a.shape != (n, 3):
        raise ValueError(f"{name} must have shape ({n}, 3), got {a.shape}")
    return a


# --- reading ------------------------------------------------------------------------------------

@dataclass(frozen=True)
class _Group:
    """Columns read together. `required`: the columns must be in the header. `nan_ok`: a cell may
    be empty or NaN. `increasing`: strictly increasing (time). `inf_ok`: a cell may be +inf (a 1-σ
    with no information: a degenerate sample)."""

    columns: tuple[str, ...]
    required: bool
    nan_ok: bool
    increasing: bool = False
    nonnegative: bool = False
    inf_ok: bool = False


_RECORDING_GROUPS = (
    _Group((T_COLUMN,), required=True, nan_ok=False, increasing=True),
    _Group(B_COLUMNS, required=True, nan_ok=False),
    _Group(M_COLUMNS, required=False, nan_ok=True),
    _Group(W_COLUMNS, required=False, nan_ok=True),
    _Group(KIT_COLUMNS, required=False, nan_ok=True),
    _Group((FLAGS_COLUMN,), required=False, nan_ok=False, nonnegative=True),
)
_RATE_GROUPS = (
    _Group((T_COLUMN,), required=True, nan_ok=False, increasing=True),
    _Group(W_COLUMNS, required=True, nan_ok=True),
    _Group(SIGMA_COLUMNS, required=True, nan_ok=True, nonnegative=True, inf_ok=True),
)


def _parse_cell(cell: str, nan_ok: bool, inf_ok: bool = False) -> float | str:
    """The cell's value, or a reason string when it is not acceptable."""
    s = cell.strip()
    if inf_ok and s.lower() in _INF_WORDS:
        return math.inf
    shown = repr(s if len(s) <= 40 else s[:37] + "...")
    if _NUMBER.fullmatch(s):
        x = float(s)
        return x if math.isfinite(x) else f"number out of range: {shown}"
    if s == "" or s.lower() in _NAN_WORDS:
        if nan_ok:
            return math.nan
        return "empty cell" if s == "" else "NaN in a required column"
    if s.lstrip("+-").lower() in ("inf", "infinity"):
        return f"infinite value {shown}"
    return f"not a number: {shown}"


def _read_table(path: PathLike, groups: Sequence[_Group]
                ) -> tuple[dict[str, np.ndarray | None], dict[str, str]]:
    """Parse a format-v1 CSV: per group (keyed by its first column) an (N, k) array, or None when an
    optional group is absent; and the metadata."""
    try:
        raw = Path(path).read_bytes()
    except OSError as e:
        raise RecordingError(path, None, None, f"cannot read: {e.strerror or e}") from e
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = raw.count(b"\n", 0, e.start) + 1
        raise RecordingError(path, line, None, f"not UTF-8 text ({e.reason} at byte {e.start})") from None

    metadata: dict[str, str] = {}
    header: list[str] | None = None
    header_line = 0
    rows: list[tuple[int, str]] = []
    previous_key = None
    for lineno, line in enumerate(text.split("\n"), start=1):
        if line.endswith("\r"):
            line = line[:-1]
        if line.startswith("#"):
            m = _META.fullmatch(line)
            if m:
                key, value = m.group(1), m.group(2).strip()
                join = key in metadata and (header is None or key == previous_key)
                metadata[key] = f"{metadata[key]}\n{value}" if join else value
                previous_key = key
            continue
        previous_key = None
        if line.strip():
            if header is None:
                header, header_line = [c.strip() for c in _split(path, lineno, line)], lineno
            else:
                rows.append((lineno, line))
    if header is None:
        raise RecordingError(path, None, None, "no header row")
    picks = _pick_columns(path, header_line, header, groups)
    out = _parse_rows_fast(rows, len(header), picks)
    if out is None:  # something is off: find it, cell by cell
        out = _parse_rows(path, rows, header, header_line, picks)
    return out, metadata


def _split(path: PathLike, lineno: int, line: str) -> list[str]:
    try:
        return next(csv.reader([line], strict=True))
    except csv.Error as e:
        raise RecordingError(path, lineno, None, f"malformed CSV: {e}") from None


def _parse_rows(path: PathLike, rows: list[tuple[int, str]], header: list[str], header_line: int,
                picks: list[tuple[_Group, list[int]]]) -> dict[str, np.ndarray | None]:
    """The reference parser: every rule, cell by cell, raising at the first broken one."""
    values: dict[str, list[list[float]]] = {g.columns[0]: [] for g, idx in picks if idx}
    for lineno, line in rows:
        cells = _split(path, lineno, line)
        if len(cells) != len(header):
            col = header[len(cells)] if len(cells) < len(header) else None
            raise RecordingError(path, lineno, col,
                                 f"{len(cells)} cells, the header (line {header_line}) has {len(header)}")
        for g, idx in picks:
            if not idx:
                continue
            row = []
            for name, i in zip(g.columns, idx):
                v = _parse_cell(cells[i], g.nan_ok, g.inf_ok)
                if isinstance(v, str):
                    raise RecordingError(path, lineno, name, v)
                if g.nonnegative and v < 0:
                    raise RecordingError(path, lineno, name, f"negative value {v!r}")
                row.append(v)
            done = values[g.columns[0]]
            if g.increasing and done and not row[0] > done[-1][0]:
                raise RecordingError(path, lineno, g.columns[0],
                                     f"time {row[0]!r} not after the previous row's {done[-1][0]!r}")
            done.append(row)
    return {g.columns[0]: np.array(values[g.columns[0]], dtype=float).reshape(-1, len(g.columns))
            if idx else None for g, idx in picks}


def _parse_rows_fast(rows: list[tuple[int, str]], ncols: int, picks: list[tuple[_Group, list[int]]]
                     ) -> dict[str, np.ndarray | None] | None:
    """Vectorised parse of a clean file (plain numbers, no quotes or spaces); None as soon as
    anything is unusual, so that `_parse_rows` reports it. Accepts a subset of what `_parse_rows`
    accepts, with the same values."""
    split = [line.split(",") for _, line in rows]
    if any(len(cells) != ncols or '"' in line for cells, (_, line) in zip(split, rows)):
        return None
    out: dict[str, np.ndarray | None] = {}
    for g, idx in picks:
        if not idx:
            out[g.columns[0]] = None
            continue
        cols = []
        for i in idx:
            cells = [c[i] for c in split]
            pattern = _COLUMN_NAN_OK if g.nan_ok else _COLUMN
            plain = [c for c in cells if c.lower() not in _INF_WORDS] if g.inf_ok else cells
            if plain and not pattern.fullmatch("\n".join(plain)):
                return None
            x = np.array([c if c else "nan" for c in cells] if g.nan_ok else cells, dtype=float)
            if (np.isinf(x).any() and not g.inf_ok) or (g.nonnegative and (x < 0).any()):
                return None
            cols.append(x)
        a = np.column_stack(cols) if cols and len(rows) else np.zeros((len(rows), len(idx)))
        if g.increasing and not (a[1:, 0] > a[:-1, 0]).all():
            return None
        out[g.columns[0]] = a
    return out


def _pick_columns(path: PathLike, lineno: int, header: list[str], groups: Sequence[_Group]
                  ) -> list[tuple[_Group, list[int]]]:
    """Indices of each group's columns in the header ([] for an absent optional group)."""
    seen: dict[str, int] = {}
    for i, name in enumerate(header):
        if name and name in seen:
            raise RecordingError(path, lineno, name, f"duplicate column (also column {seen[name] + 1})")
        seen[name] = i
    picks = []
    for g in groups:
        present = [c for c in g.columns if c in seen]
        if g.required or present:
            for c in g.columns:
                if c not in seen:
                    why = "missing required column" if g.required else \
                        f"missing column (the group {', '.join(g.columns)} must be complete)"
                    raise RecordingError(path, lineno, c, why)
            picks.append((g, [seen[c] for c in g.columns]))
        else:
            picks.append((g, []))
    return picks


def read_recording(path: PathLike, *, check_units: bool = False) -> Recording:
    """Read a recording-format-v1 CSV (µT, N·m, °/s in the file) into SI arrays.

    Raises RecordingError (file, line, column) on anything the format forbids. `check_units`: also
    refuse field columns that are evidently not in µT (`fsw.estimation.field_check.PLAUSIBLE_UT`, the
    check the estimating tools make); synthetic data (a zero field) may not pass it.
    """
    cols, metadata = _read_table(path, _RECORDING_GROUPS)
    t = cols[T_COLUMN][:, 0]
    m = cols[M_COLUMNS[0]]
    w = cols[W_COLUMNS[0]]
    kit = cols[KIT_COLUMNS[0]]
    flags = cols[FLAGS_COLUMN]
    if flags is not None:
        flags = flags[:, 0]
        odd = (flags != np.round(flags)) | (flags > 0xFF)
        if odd.any():
            raise RecordingError(path, _data_line(path, int(np.argmax(odd))), FLAGS_COLUMN,
                                 f"not a flags byte: {flags[int(np.argmax(odd))]!r}")
        flags = flags.astype(np.int64)
    if check_units:
        _check_field_units(path, cols[B_COLUMNS[0]])
    return Recording(t_s=t, b_T=cols[B_COLUMNS[0]] * T_PER_UT,
                     m_Nm=None if m is None else m,
                     w_ref_radps=None if w is None else np.deg2rad(w),
                     metadata=metadata, path=Path(path),
                     kit_T=None if kit is None else kit * T_PER_UT, flags=flags)


def _check_field_units(path: PathLike, b_uT: np.ndarray) -> None:
    """Refuse a file whose field columns are evidently not in µT (`field_check.refusal`: tesla or
    gauss, far too small; nT, far too large), naming the first data line whose |B| is off."""
    if not len(b_uT):
        return
    why = field_check.refusal(field_check.median_uT(b_uT * T_PER_UT))
    if why is None:
        return
    mag = np.linalg.norm(b_uT, axis=1)
    lo, hi = field_check.PLAUSIBLE_UT
    i = int(np.argmax((mag < lo) if np.median(mag) < lo else (mag > hi)))
    raise RecordingError(path, _data_line(path, i), B_COLUMNS[0], why)


def _data_line(path: PathLike, index: int) -> int | None:
    """1-based line of the index-th data row (after comments, blank lines and the header)."""
    seen = -1
    for lineno, line in enumerate(Path(path).read_text(encoding="utf-8-sig").split("\n"), start=1):
        if line.startswith("#") or not line.strip():
            continue
        if seen == index:
            return lineno
        seen += 1
    return None


def read_rate_estimates(path: PathLike) -> RateEstimates:
    """Read a rate-estimate CSV (°/s in the file) into rad/s; NaN where no estimate exists, σ = inf
    (``inf`` in a σ column) where an estimator had no information."""
    cols, metadata = _read_table(path, _RATE_GROUPS)
    return RateEstimates(t_s=cols[T_COLUMN][:, 0], w_radps=np.deg2rad(cols[W_COLUMNS[0]]),
                         sigma_radps=np.deg2rad(cols[SIGMA_COLUMNS[0]]),
                         metadata=metadata, path=Path(path))


# --- writing ------------------------------------------------------------------------------------

def _metadata_lines(path: PathLike, metadata: dict[str, str]) -> list[str]:
    out = []
    for key, value in metadata.items():
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_.\-]*", key):
            raise RecordingError(path, None, None, f"metadata key {key!r} is not a plain name")
        for part in str(value).split("\n"):
            try:
                part.encode("utf-8")
            except UnicodeEncodeError:
                raise RecordingError(path, None, None, f"metadata {key!r} is not encodable as UTF-8") from None
            out.append(f"# {key}: {part.strip()}")
    return out


def _format_exact(x: float) -> str:
    """Shortest text that reads back as exactly the same float (used for time, which must stay
    strictly increasing)."""
    return repr(float(x))


def _format(x: float) -> str:
    """15 significant digits: hides the last-bit noise of unit conversions (0.406 µT → T → µT
    reads 0.406, not 0.40599999999999997) and is far below any sensor's resolution; NaN as ``nan``."""
    if math.isnan(x):
        return "nan"
    text = f"{x:.15g}"
    return text if math.isfinite(float(text)) else repr(x)  # near the float limit: do not round to inf


def _table_lines(path: PathLike, metadata: dict[str, str],
                 blocks: Sequence[tuple[_Group, np.ndarray]]) -> list[str]:
    """Lines of a CSV made of column blocks (group, (N, k) values in file units); the first block is
    the time. The values are checked exactly as the reader checks them."""
    lines = _metadata_lines(path, metadata)
    names = [c for g, _ in blocks for c in g.columns]
    lines.append(",".join(names))
    table = np.hstack([v for _, v in blocks])
    lines.extend(_row_lines(path, [g for g, _ in blocks], table, len(lines) + 1))
    return lines


def _row_lines(path: PathLike, groups: Sequence[_Group], table: np.ndarray, first_row_line: int,
               previous_t: float | None = None) -> list[str]:
    """Rows of a table (file units) as CSV lines, checked as the reader checks them (`previous_t`: the
    time of the row before, already written)."""
    names = [c for g in groups for c in g.columns]
    nan_ok = np.array([g.nan_ok for g in groups for _ in g.columns])
    inf_ok = np.array([g.inf_ok for g in groups for _ in g.columns])
    nonneg = np.array([g.nonnegative for g in groups for _ in g.columns])
    with np.errstate(invalid="ignore"):
        bad = ((np.isinf(table) & ~inf_ok) | (np.isnan(table) & ~nan_ok) | ((table < 0) & nonneg))
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise RecordingError(path, first_row_line + int(r), names[c], f"cannot write {table[r, c]!r}")
    t = table[:, 0] if previous_t is None else np.concatenate([[previous_t], table[:, 0]])
    later = t[1:] > t[:-1]
    if not later.all():
        r = int(np.argmin(later)) + 1
        row = r - (previous_t is not None)
        raise RecordingError(path, first_row_line + row, names[0],
                             f"time {t[r]!r} not after the previous row's {t[r - 1]!r}")
    return _lines(table)


#: finite values above this may round to inf at 15 digits: `_format` takes them one by one
_NEAR_MAX = 1.7976931348623e308


def _lines(table: np.ndarray) -> list[str]:
    """The rows as `_format_exact` (time) and `_format` (the rest) write them, one %-format a row (the
    same text: %r is repr, %.15g writes NaN as nan and ±inf as inf), rows with a value near the float
    limit one value at a time."""
    rows = table.tolist()
    fmt = "%r" + ",%.15g" * (table.shape[1] - 1)
    lines = [fmt % tuple(row) for row in rows]
    with np.errstate(invalid="ignore"):
        near = np.isfinite(table[:, 1:]) & (np.abs(table[:, 1:]) > _NEAR_MAX)
    for r in np.flatnonzero(near.any(axis=1)):
        lines[r] = ",".join([_format_exact(rows[r][0]), *map(_format, rows[r][1:])])
    return lines


class _Appender:
    """A format-v1 CSV written while its rows arrive: metadata and header when opened, then rows in
    time order, each batch with one write(2) of whole lines. A process killed at any moment leaves a
    file that reads up to its last complete row; nothing is buffered in the process."""

    def __init__(self, path: PathLike, groups: Sequence[_Group], metadata: dict[str, str]) -> None:
        self.path = Path(path)
        self.groups = tuple(groups)
        lines = _metadata_lines(path, metadata)
        lines.append(",".join(c for g in groups for c in g.columns))
        self.line = len(lines)  # lines in the file so far
        self.rows = 0
        self.last_t: float | None = None
        self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        self._write(lines)

    def _write(self, lines: list[str]) -> None:
        data = ("\n".join(lines) + "\n").encode("utf-8")
        while data:
            n = os.write(self._fd, data)
            data = data[n:]

    def _append(self, table: np.ndarray) -> None:
        if not len(table):
            return
        lines = _row_lines(self.path, self.groups, table, self.line + 1, self.last_t)
        self._write(lines)
        self.line += len(lines)
        self.rows += len(lines)
        self.last_t = float(table[-1, 0])

    def comment(self, key: str, value: str) -> None:
        """A ``# key: value`` line after the rows (the reader takes metadata from any comment line)."""
        self.comments({key: value})

    def comments(self, metadata: dict[str, str]) -> None:
        """``# key: value`` lines after the rows, in one write: each replaces the key's earlier value for
        the reader (a key learnt or changed while recording)."""
        lines = _metadata_lines(self.path, metadata)
        if lines:
            self._write(lines)
            self.line += len(lines)

    def close(self) -> None:
        if self._fd >= 0:
            os.fsync(self._fd)
            os.close(self._fd)
            self._fd = -1


class RecordingAppender(_Appender):
    """A recording written row by row (SI in, µT / N·m / °/s in the file); `truth`: with the moment and
    reference-rate columns; `kit`: with the kit-field and flags columns."""

    def __init__(self, path: PathLike, metadata: dict[str, str], *, truth: bool, kit: bool = False) -> None:
        t, b, m, w, k, f = _RECORDING_GROUPS
        super().__init__(path, (t, b) + ((m, w) if truth else ()) + ((k, f) if kit else ()), metadata)
        self.truth = truth
        self.kit = kit

    def append(self, t_s, b_T, m_Nm=None, w_ref_radps=None, kit_T=None, flags=None) -> None:
        cols = [np.asarray(t_s, dtype=float)[:, None], np.asarray(b_T, dtype=float) / T_PER_UT]
        if self.truth:
            cols += [np.asarray(m_Nm, dtype=float), np.rad2deg(np.asarray(w_ref_radps, dtype=float))]
        if self.kit:
            cols += [np.asarray(kit_T, dtype=float) / T_PER_UT, np.asarray(flags, dtype=float)[:, None]]
        self._append(np.hstack(cols))


class RateAppender(_Appender):
    """Rate estimates written row by row (rad/s in, °/s in the file)."""

    def __init__(self, path: PathLike, metadata: dict[str, str]) -> None:
        super().__init__(path, _RATE_GROUPS, metadata)

    def append(self, t_s, w_radps, sigma_radps) -> None:
        self._append(np.hstack([np.asarray(t_s, dtype=float)[:, None], np.rad2deg(np.asarray(w_radps, dtype=float)),
                                np.rad2deg(np.asarray(sigma_radps, dtype=float))]))


def write_recording(path: PathLike, rec: Recording) -> None:
    """Write `rec` as recording format v1: metadata comments, header, one row per sample (µT, N·m,
    °/s). The moment columns are written when any moment is non-zero, the reference columns when
    `w_ref_radps` is given, the kit columns and flags when `kit_T` / `flags` are. Atomic; raises
    RecordingError, writing nothing, on data the reader would reject."""
    t, b, m, w, k, f = _RECORDING_GROUPS
    blocks = [(t, rec.t_s[:, None]), (b, rec.b_T / T_PER_UT)]
    if np.any(rec.m_Nm != 0.0):  # NaN != 0: unknown moments are written too
        blocks.append((m, rec.m_Nm))
    if rec.w_ref_radps is not None:
        blocks.append((w, np.rad2deg(rec.w_ref_radps)))
    if rec.kit_T is not None:
        blocks.append((k, rec.kit_T / T_PER_UT))
    if rec.flags is not None:
        blocks.append((f, rec.flags.astype(float)[:, None]))
    write_atomic(path, _table_lines(path, rec.metadata, blocks))


def write_rate_estimates(path: PathLike, est: RateEstimates) -> None:
    """Write rate estimates (°/s) with their 1-σ; NaN allowed where no estimate exists, σ = inf
    (written ``inf``) where an estimator has no information (a degenerate sample). Atomic; raises
    RecordingError, writing nothing, on an infinite rate, negative σ or non-increasing time."""
    t, w, s = _RATE_GROUPS
    blocks = [(t, est.t_s[:, None]), (w, np.rad2deg(est.w_radps)), (s, np.rad2deg(est.sigma_radps))]
    write_atomic(path, _table_lines(path, est.metadata, blocks))
