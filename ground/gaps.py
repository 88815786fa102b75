"""Numbered samples on the ground: which have arrived, which are missing, and asking the box again.

The box numbers every sample it sends (DEBRIS_MAG_SAMPLE.seq) and keeps it in its sample store
(`fsw.telemetry.sample_store`). :class:`SeqGaps` keeps, per run of the flight software, the numbers
that arrived and the ones known to exist (a later number arrived, or DEBRIS_SAMPLE_STORE's
``next_seq`` says so) but are missing. Its ``watermark`` is the first number not yet settled: every
sample below it has arrived or has been given up, so the rows below it can go into the recording in
order. :class:`GapRequester` turns the missing numbers into DEBRIS_SAMPLE_REQUEST ranges: a number is
asked for after it has been missing for `hold_s` (reordering on the link settles first), again every
`retry_s`, and given up after `max_attempts` or as soon as the box says it no longer holds it. What
is asked per call is bounded (`max_ranges` ranges of at most `fsw.telemetry.sample_store.MAX_REQUEST`),
so a long outage costs the uplink a few frames a second, not a burst.
"""
from __future__ import annotations

from fsw.telemetry.sample_store import MAX_REQUEST

#: the most numbers a run may grow by at once, forward or back (see `SeqGaps.add`)
MAX_JUMP = 100_000


class SeqGaps:
    """Arrived, missing and given-up sample numbers of one run."""

    def __init__(self) -> None:
        self.lo: int | None = None  # first number wanted
        self.end = 0  # numbers below this are known to exist
        self.watermark: int | None = None  # first number neither arrived nor given up
        self._above: set[int] = set()  # arrived at or above the watermark
        self.given_up: set[int] = set()
        self.filled_late = 0  # given up, then arrived after all
        self.arrived = 0
        self.strays = 0

    def add(self, seq: int) -> bool:
        """Record an arrival; False when it is a duplicate. A number far before the start or far past
        the end (`MAX_JUMP`: no radio loses that many in a row; a forged or corrupted frame) is taken as a
        sample but neither widens the run nor makes its numbers missing (counted in `strays`)."""
        if self.lo is None:
            self.lo = self.watermark = seq
        elif not self.lo - MAX_JUMP <= seq <= self.end + MAX_JUMP:
            self.strays += 1
            return True
        elif seq < self.lo:  # before the start of the recording: it widens the run
            self.start_at(seq)
        if seq < self.watermark:
            if seq in self.given_up:
                self.given_up.discard(seq)
                self.filled_late += 1
                self.arrived += 1
                return True
            return False
        if seq in self._above:
            return False
        self._above.add(seq)
        self.arrived += 1
        self.end = max(self.end, seq + 1)
        self._advance()
        return True

    def extend(self, end: int) -> None:
        """Numbers below `end` exist (the box sent them once)."""
        if self.lo is not None and self.end < end <= self.end + MAX_JUMP:
            self.end = end

    def start_at(self, lo: int) -> None:
        """Want the numbers from `lo` on (before the first that arrived)."""
        if self.lo is None or lo >= self.lo:
            return
        settled = range(self.lo, self.watermark)  # arrived or given up: still settled
        self._above.update(s for s in settled if s not in self.given_up)
        self.lo = self.watermark = lo
        self._advance()

    def _advance(self) -> None:
        w = self.watermark
        above, given_up = self._above, self.given_up
        while w in above or w in given_up:
            above.discard(w)
            w += 1
        self.watermark = w

    def missing(self, limit: int = 5000) -> list[int]:
        """Numbers known to exist that have neither arrived nor been given up (at most `limit`)."""
        if self.watermark is None:
            return []
        out = []
        s = self.watermark
        while s < self.end and len(out) < limit:
            if s not in self._above and s not in self.given_up:
                out.append(s)
            s += 1
        return out

    def give_up(self, seqs) -> None:
        for s in seqs:
            if self.watermark is not None and s >= self.watermark and s not in self._above:
                self.given_up.add(s)
        self._advance()

    def give_up_all(self) -> None:
        self.give_up(self.missing(limit=1 << 62))


class GapRequester:
    """When to ask for which missing numbers, and when to stop asking."""

    def __init__(self, *, hold_s: float = 1.0, retry_s: float = 2.0, max_attempts: int = 20,
                 max_ranges: int = 4) -> None:
        self.hold_s = hold_s
        self.retry_s = retry_s
        self.max_attempts = max_attempts
        self.max_ranges = max_ranges
        self._asked: dict[int, tuple[int, float]] = {}  # seq -> (attempts, time of the last)
        self.requests = 0
        self.samples_asked = 0
        self.given_up = 0

    def due(self, gaps: SeqGaps, now_s: float, stored_first_seq: int | None = None) -> list[tuple[int, int]]:
        """The (first, count) ranges to ask for now; numbers past hope are given up in `gaps`."""
        want, hopeless = [], []
        for seq in gaps.missing():
            if stored_first_seq is not None and seq < stored_first_seq:
                hopeless.append(seq)
                continue
            n, last = self._asked.get(seq, (0, None))
            if last is None:
                self._asked[seq] = (0, now_s)  # first seen missing: let reordering settle
            elif now_s - last >= (self.hold_s if n == 0 else self.retry_s):
                if n >= self.max_attempts:
                    hopeless.append(seq)
                else:
                    want.append(seq)
        if hopeless:
            gaps.give_up(hopeless)
            self.given_up += len(hopeless)
            for s in hopeless:
                self._asked.pop(s, None)
        ranges: list[tuple[int, int]] = []
        for seq in want:
            if ranges and seq == ranges[-1][0] + ranges[-1][1] and ranges[-1][1] < MAX_REQUEST:
                ranges[-1] = (ranges[-1][0], ranges[-1][1] + 1)
            elif len(ranges) < self.max_ranges:
                ranges.append((seq, 1))
            else:
                break
        for first, count in ranges:
            for s in range(first, first + count):
                self._asked[s] = (self._asked[s][0] + 1, now_s)
            self.requests += 1
            self.samples_asked += count
        return ranges

    def arrived(self, seq: int) -> None:
        self._asked.pop(seq, None)
