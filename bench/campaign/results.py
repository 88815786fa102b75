"""The per-run results file: Parquet through pyarrow, one row a run.

Columns: ``run_id``, ``seed`` (the run's seed entropy, a JSON list of integers), ``params`` (its parameters as
canonical JSON), ``result`` (what the run returned, as JSON with numpy arrays base64-encoded: exact, every
float64 bit kept),
``p.<name>`` and ``r.<name>`` (the scalar parameters and scalar results again as typed columns, for tables
and plots in any Parquet reader), and ``elapsed_s``, ``cpu_s`` and ``worker`` (how long, on which worker:
the only columns that differ between two runs of a campaign). The file's metadata holds the campaign's configuration;
a results file is only ever continued by the same campaign.

Appending: a Parquet file is written whole (its footer last), so each completed run is written at once as
its own small file in ``FILE.parts/`` (atomically: a run is there whole or not at all), and the parts are
merged into FILE (atomically) when the campaign ends or next starts. A crash loses no completed run; a
re-started campaign with the same FILE skips the runs already there.
"""
from __future__ import annotations

import base64
import itertools
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from bench.campaign.runs import Run
from fsw.files import atomic_file

META_KEY = b"debris_box.campaign"
_ND = "__ndarray__"
_part_numbers = itertools.count()


class ResultsError(Exception):
    """A results file that cannot be read or belongs to another campaign (one line, for the user)."""


def _to_json(o):
    if isinstance(o, np.ndarray):
        if o.dtype == object:
            raise TypeError("object arrays cannot be stored")
        a = np.ascontiguousarray(o)
        return {_ND: base64.b64encode(a.tobytes()).decode("ascii"), "dtype": a.dtype.str, "shape": list(a.shape)}
    if isinstance(o, dict):
        return {str(k): _to_json(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_to_json(v) for v in o]
    if isinstance(o, np.generic):
        return o.item()
    return o


def _from_json(o):
    if isinstance(o, dict):
        if _ND in o:
            return np.frombuffer(base64.b64decode(o[_ND]), dtype=np.dtype(o["dtype"])).reshape(o["shape"]).copy()
        return {k: _from_json(v) for k, v in o.items()}
    if isinstance(o, list):
        return [_from_json(v) for v in o]
    return o


def encode(result) -> str:
    """A run's result as text: JSON (floats written in full, NaN and ±inf kept) with arrays as raw bytes."""
    return json.dumps(_to_json(result), separators=(",", ":"), allow_nan=True)


def decode(text: str):
    return _from_json(json.loads(text))


def _scalar(v) -> bool:
    return isinstance(v, (bool, int, float, str, np.bool_, np.integer, np.floating)) and not isinstance(v, bytes)


def row(run: Run, result, *, elapsed_s: float, worker: str, cpu_s: float = float("nan")) -> dict:
    """The results file's row of `run` that returned `result`."""
    out = {"run_id": run.id, "seed": run.seed_json(), "params": run.params_json(), "result": encode(result),
           "elapsed_s": float(elapsed_s), "cpu_s": float(cpu_s), "worker": worker}
    out.update({f"p.{k}": (v.item() if isinstance(v, np.generic) else v) for k, v in run.params.items() if _scalar(v)})
    if isinstance(result, dict):
        out.update({f"r.{k}": (v.item() if isinstance(v, np.generic) else v) for k, v in result.items()
                    if _scalar(v)})
    return out


def _seed_text(stored) -> str:
    """A stored seed as JSON text (files written before the seed became text hold a list of integers)."""
    return stored if isinstance(stored, str) else json.dumps(list(stored))


class ResultsFile:
    """The results file at `path` of the campaign configured by `config` (a JSON-able dict: whatever,
    besides the runs' own seeds and parameters, decides the results)."""

    def __init__(self, path, config: dict) -> None:
        self.path = Path(path)
        self.parts = Path(str(path) + ".parts")
        self.config_json = json.dumps(config, sort_keys=True, default=str)

    def _read(self, path: Path) -> pa.Table:
        try:
            table = pq.read_table(path)
        except (OSError, pa.ArrowException) as e:
            raise ResultsError(f"{path}: not a readable Parquet results file ({e})") from None
        meta = (table.schema.metadata or {}).get(META_KEY)
        if meta is None or "run_id" not in table.column_names:
            raise ResultsError(f"{path}: not a campaign results file")
        if meta.decode() != self.config_json:
            raise ResultsError(f"{path} holds the results of another campaign (configuration "
                               f"{meta.decode()[:200]}); give another --results file")
        return table

    def load(self) -> dict[str, dict]:
        """The rows already stored, by run id (the parts of an interrupted campaign included)."""
        tables = [self._read(self.path)] if self.path.exists() else []
        if self.parts.is_dir():
            tables += [self._read(p) for p in sorted(self.parts.glob("*.parquet"))]
        rows: dict[str, dict] = {}
        for t in tables:
            for r in t.to_pylist():
                rows.setdefault(r["run_id"], r)
        return rows

    def check(self, runs: list[Run], stored: dict[str, dict]) -> None:
        """Refuse stored rows whose run, by the same id, has another seed or other parameters."""
        for run in runs:
            r = stored.get(run.id)
            if r is not None and (_seed_text(r["seed"]) != run.seed_json() or r["params"] != run.params_json()):
                raise ResultsError(f"{self.path}: run {run.id} was stored with seed {r['seed']} and parameters "
                                   f"{r['params']}, this campaign has {run.seed_json()} and {run.params_json()}; "
                                   "give another --results file")

    def _write(self, path: Path, rows: list[dict]) -> None:
        table = pa.Table.from_pylist(rows)
        table = table.replace_schema_metadata({META_KEY: self.config_json.encode()})
        with atomic_file(path, "wb") as f:
            pq.write_table(table, f)

    def append(self, r: dict) -> None:
        """One completed run, at once (a file of its own in FILE.parts/, written whole or not at all)."""
        self.parts.mkdir(exist_ok=True)
        self._write(self.parts / f"part-{os.getpid()}-{next(_part_numbers):08d}.parquet", [r])

    def consolidate(self, order: list[str] | None = None) -> None:
        """Merge FILE and its parts into FILE (rows in the campaign's `order`, then any others), the parts
        removed after."""
        if not self.parts.is_dir():
            return
        rows = self.load()
        rank = {rid: i for i, rid in enumerate(order or [])}
        ordered = sorted(rows.values(), key=lambda r: (rank.get(r["run_id"], len(rank)), r["run_id"]))
        if ordered:
            tables = [self._table([r]) for r in ordered]
            table = pa.concat_tables(tables, promote_options="permissive")
            table = table.replace_schema_metadata({META_KEY: self.config_json.encode()})
            with atomic_file(self.path, "wb") as f:
                pq.write_table(table, f)
        shutil.rmtree(self.parts, ignore_errors=True)

    @staticmethod
    def _table(rows: list[dict]) -> pa.Table:
        return pa.Table.from_pylist(rows)


def read(path) -> tuple[dict, pa.Table]:
    """A results file's campaign configuration and its table (for reports)."""
    try:
        table = pq.read_table(path)
    except (OSError, pa.ArrowException) as e:
        raise ResultsError(f"{path}: not a readable Parquet results file ({e})") from None
    meta = (table.schema.metadata or {}).get(META_KEY)
    if meta is None:
        raise ResultsError(f"{path}: not a campaign results file")
    return json.loads(meta), table
