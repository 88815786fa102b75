"""The box's sample store: every magnetometer sample handed to telemetry is numbered and kept, so that
the ground can ask again for what a lossy radio did not deliver (DEBRIS_SAMPLE_REQUEST) and the
recording on the ground ends complete.

- :class:`SampleStore`: a ring of the last `capacity` samples (number, run, time, field, the sample's
  DEBRIS_SAMPLE_FLAGS and the de-orbit kit's field the box took out of it), preallocated: a sample sent
  again carries its flag (KIT_MOVING) and its kit field as it did live.
  With a `path` the ring lives in a file (memory-mapped) that survives a restart: the numbering goes
  on where the previous run stopped and the previous runs' samples can still be sent. The file is
  written in place, sample by sample, and its header (the next number) after the sample: a process
  killed between the two leaves a sample the header does not yet count, never a counted sample that is
  not there. A store file of another layout or capacity, or cut short, is not loaded: it is moved aside
  (``.bad``) and a new store begins; a file that is not a sample store at all is never touched (the
  samples are then kept in memory). `reset_reason` says which.
- :class:`Resender`: the ground's requests (ranges of sample numbers) in a bounded queue, served from
  the store within a byte budget per second (token bucket, one second deep), after the live telemetry.
  A request for samples the store no longer has is answered with what it still has; the ground learns
  the store's oldest number from DEBRIS_SAMPLE_STORE.

Nothing here allocates per sample or raises into the flight loop.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

DEFAULT_CAPACITY = 65536
#: the most samples one request may ask for (DEBRIS_SAMPLE_REQUEST.count)
MAX_REQUEST = 1000
DEFAULT_RESEND_BYTES_PER_S = 1000.0

_MAGIC = b"DEBRIS-SAMPLES-2"
_MAGIC_PREFIX = b"DEBRIS-SAMPLES-"  # any layout of a store: a file of an older one is moved aside
_HEADER = np.dtype([("magic", "S16"), ("capacity", "<u8"), ("next_seq", "<u8")])
_RECORD = np.dtype([("seq", "<u8"), ("run_id", "<u4"), ("flags", "<u4"), ("t_us", "<u8"), ("b_T", "<f8", (3,)),
                    ("kit_T", "<f8", (3,))])


def _has_magic(p: Path) -> bool:
    try:
        with open(p, "rb") as f:
            return f.read(len(_MAGIC)).startswith(_MAGIC_PREFIX)
    except OSError:
        return False


class SampleStore:
    """Numbered samples, the last `capacity` of them; in a file when `path` is given."""

    def __init__(self, capacity: int = DEFAULT_CAPACITY, *, run_id: int = 0, path: str | os.PathLike | None = None
                 ) -> None:
        if capacity < 1:
            raise ValueError("sample store capacity must be >= 1")
        self.capacity = int(capacity)
        self.run_id = int(run_id) & 0xFFFFFFFF
        self.path = None if path is None else Path(path)
        self.reset_reason = ""
        self._map = None
        if self.path is not None:
            self._open_file()
        if self._map is None:
            self._header = np.zeros(1, dtype=_HEADER)
            self._records = np.zeros(self.capacity, dtype=_RECORD)
        self._header["magic"] = _MAGIC
        self._header["capacity"] = self.capacity
        self._next = int(self._header["next_seq"][0])
        self.run_first_seq = self._next
        # plain views of the record fields: assignments into them do not allocate
        r = self._records
        self._seq, self._run, self._t_us, self._b = r["seq"], r["run_id"], r["t_us"], r["b_T"]
        self._flags, self._kit = r["flags"], r["kit_T"]

    def _open_file(self) -> None:
        size = _HEADER.itemsize + self.capacity * _RECORD.itemsize
        p = self.path
        if p.exists() or p.is_symlink():
            if not p.is_file() or p.is_symlink() or not _has_magic(p):  # somebody else's file: never touched
                self.reset_reason = f"{p}: not a sample store, left alone; samples kept in memory only"
                self.path = None
                return
            why = self._unusable(p, size)
            if why:
                self.reset_reason = f"{p}: {why}; moved to {p.name}.bad, a new store begins"
                os.replace(p, p.with_name(p.name + ".bad"))
        if not p.exists():
            with open(p, "wb") as f:
                f.truncate(size)
        self._map = np.memmap(p, dtype=np.uint8, mode="r+", shape=(size,))
        self._header = self._map[:_HEADER.itemsize].view(_HEADER)
        self._records = self._map[_HEADER.itemsize:].view(_RECORD)

    def _unusable(self, p: Path, size: int) -> str:
        """Why a store file (it has the magic) cannot be continued, or ""."""
        if p.stat().st_size != size:
            return f"{p.stat().st_size} bytes, a store of {self.capacity} samples has {size}"
        head = np.fromfile(p, dtype=_HEADER, count=1)
        if bytes(head["magic"][0]) != _MAGIC:
            return f"another layout ({bytes(head['magic'][0]).decode('ascii', 'replace')})"
        if int(head["capacity"][0]) != self.capacity:
            return f"capacity {int(head['capacity'][0])}, not {self.capacity}"
        return ""

    # --- state ------------------------------------------------------------------------------------
    @property
    def next_seq(self) -> int:
        return self._next

    @property
    def first_seq(self) -> int:
        """The oldest number still held."""
        return max(0, self.next_seq - self.capacity)

    @property
    def persistent(self) -> bool:
        return self._map is not None

    def __len__(self) -> int:
        return self.next_seq - self.first_seq

    # --- writing ----------------------------------------------------------------------------------
    def append(self, t_s: float, b_T, flags: int = 0, kit_T=None) -> int:
        """Keep one sample (`flags`: its DEBRIS_SAMPLE_FLAGS; `kit_T`: the kit's field taken out of it,
        T, None: none); its number."""
        seq = self._next
        k = seq % self.capacity
        self._t_us[k] = int(round(t_s * 1e6))
        self._b[k] = b_T
        self._flags[k] = int(flags)
        if kit_T is None:
            self._kit[k] = 0.0
        else:
            self._kit[k] = kit_T
        self._run[k] = self.run_id
        self._seq[k] = seq
        self._next = seq + 1
        self._header["next_seq"] = self._next
        return seq

    def get(self, seq: int):
        """(run id, time µs, field T as a view, flags, kit field T as a view) of sample `seq`, or None when
        it is not held."""
        if not self.first_seq <= seq < self.next_seq:
            return None
        k = seq % self.capacity
        if int(self._seq[k]) != seq:  # a slot the previous run did not finish writing
            return None
        return int(self._run[k]), int(self._t_us[k]), self._b[k], int(self._flags[k]), self._kit[k]

    def sync(self) -> None:
        """Write the file's dirty pages out (once a second from the status task)."""
        if self._map is not None:
            try:
                self._map.flush()
            except OSError:
                pass

    def close(self) -> None:
        self.sync()
        self._map = None


class Resender:
    """Requested sample numbers, served from a :class:`SampleStore` within `bytes_per_s`."""

    def __init__(self, store: SampleStore, *, bytes_per_s: float = DEFAULT_RESEND_BYTES_PER_S,
                 max_ranges: int = 64) -> None:
        self.store = store
        self.bytes_per_s = float(bytes_per_s)
        self.max_ranges = int(max_ranges)
        self._ranges: list[list[int]] = []  # [next, end) each, in arrival order
        self._tokens = 0.0
        self._now_s: float | None = None
        self.requests = 0
        self.refused = 0
        self.resent = 0
        self.unavailable = 0  # requested numbers the store did not hold

    @property
    def queued(self) -> int:
        return sum(end - nxt for nxt, end in self._ranges)

    def request(self, first_seq: int, count: int) -> bool:
        """Queue first_seq .. first_seq + count − 1 (merged with what is queued); False (counted) when the
        request is malformed or the queue is full."""
        first_seq, count = int(first_seq), int(count)
        end = min(first_seq + count, self.store.next_seq)
        if count < 1 or count > MAX_REQUEST or first_seq < 0 or first_seq >= end:
            self.refused += 1
            return False
        for r in self._ranges:
            if first_seq < r[1] and r[0] < end:  # overlaps a queued range: widen it
                r[0], r[1] = min(r[0], first_seq), max(r[1], end)
                self.requests += 1
                return True
        if len(self._ranges) >= self.max_ranges:
            self.refused += 1
            return False
        self._ranges.append([first_seq, end])
        self.requests += 1
        return True

    def service(self, now_s: float, send) -> None:
        """Send what the budget allows: `send(seq, run_id, t_us, b_T, flags, kit_T) -> bytes written or None` (None:
        the link is down; try again next tick)."""
        if self._now_s is not None:
            self._tokens = min(self._tokens + max(0.0, now_s - self._now_s) * self.bytes_per_s, self.bytes_per_s)
        self._now_s = now_s
        while self._ranges and self._tokens > 0.0:
            r = self._ranges[0]
            oldest = self.store.first_seq
            if r[0] < oldest:  # gone from the store: skip the whole part at once
                self.unavailable += min(oldest, r[1]) - r[0]
                r[0] = oldest
            elif (rec := self.store.get(r[0])) is None:
                self.unavailable += 1
                r[0] += 1
            else:
                n = send(r[0], *rec)
                if n is None:  # link down: the same number next time
                    return
                self.resent += 1
                self._tokens -= n
                r[0] += 1
            if r[0] >= r[1]:
                self._ranges.pop(0)
