"""The boxes a station watches: frames routed by system id to each box's view (`ground.web.boxview`), each
checked with that box's own key.

Keys (`Fleet(keys=…, default_key=…)`): ``keys`` maps a system id to its key (``--box SYSID:KEYFILE``);
``default_key`` (``--key FILE``) is the key of every other system id. With ``keys`` and no default key only
the listed boxes are shown; frames of other system ids are counted (``other_frames``) and archived, not
shown. Without any key, frames are not verified (the page says "not verified"). A box is shown once it
sent an authentic frame (listed boxes from the start), at most `MAX_BOXES` of them: a flood of forged
system ids makes no views, only counts.

Thread safety: `handle` (the ingest thread) and `update` / `snapshot` (the web server's loop) take the
fleet's lock; the JSON they return holds values, counters and names, never a key.
"""
from __future__ import annotations

import threading
from collections import Counter

from fsw.telemetry.dialect import mavlink

from ..link_stats import LinkStats
from .boxview import BoxView

#: the most boxes shown at once
MAX_BOXES = 32


class Fleet:
    def __init__(self, keys: dict[int, bytes] | None = None, default_key: bytes | None = None, *,
                 method: int = mavlink.DEBRIS_RATE_METHOD_KALMAN, window_s: float = 600.0) -> None:
        self._keys = dict(keys or {})
        self._default_key = default_key
        self._only_listed = bool(self._keys) and default_key is None
        self.method, self.window_s = method, window_s
        self.lock = threading.Lock()
        self.boxes: dict[int, BoxView] = {s: self._view(s) for s in sorted(self._keys)}
        #: link-level accounting of what frames nothing (garbage, bad CRC) and of system ids not shown
        self.link = LinkStats()
        self.other_frames: Counter[int] = Counter()
        self.frames = 0
        self.seq = 0
        #: frames the station could not take in time (the ingest queue full), from `ground.station`
        self.dropped = 0
        self.archive: dict = {}
        #: frames the view failed on, by message type and error (`failed`)
        self.failures: Counter[str] = Counter()

    def _view(self, sysid: int) -> BoxView:
        key = self._keys.get(sysid, self._default_key)
        return BoxView(sysid, key, method=self.method, window_s=self.window_s)

    @property
    def verified(self) -> bool:
        return bool(self._keys) or self._default_key is not None

    def handle(self, msg, now_s: float) -> None:
        """One message from a link (BAD_DATA included), received at `now_s` (Unix time)."""
        with self.lock:
            self.frames += 1
            if msg.get_msgId() < 0:
                self.link.on_bad_data(msg)
                return
            sysid = msg.get_srcSystem()
            box = self.boxes.get(sysid)
            if box is None:
                if self._only_listed or len(self.boxes) >= MAX_BOXES:
                    self.other_frames[sysid] += 1
                    return
                box = self._view(sysid)
                box.handle(msg, now_s)
                if box.authentic:
                    self.boxes[sysid] = box
                else:
                    self.other_frames[sysid] += 1
                return
            box.handle(msg, now_s)

    def failed(self, msg, error: Exception, say) -> None:
        """A frame the view could not take (a fault of the view, not of the frame: it is archived): counted,
        the first of each kind said, the station goes on."""
        with self.lock:
            kind = f"{msg.get_type()}: {type(error).__name__}"
            if kind not in self.failures:
                say(f"the view could not take a {kind} ({error}); counted, the station goes on")
            self.failures[kind] += 1

    def _station(self) -> dict:
        link = self.link
        return {"frames": self.frames, "verified": self.verified, "boxes": sorted(self.boxes),
                "other_frames": sum(self.other_frames.values()),
                "other_systems": len(self.other_frames),
                "garbage_bytes": link.garbage_bytes, "bad_crc": link.bad_crc, "malformed": link.malformed,
                "dropped": self.dropped, "view_failures": sum(self.failures.values()), "archive": dict(self.archive)}

    def update(self, now_s: float) -> dict:
        """The boxes' changes since the last update (published rows decimated, state, new events)."""
        with self.lock:
            self.seq += 1
            boxes = {}
            for sysid, box in self.boxes.items():
                u = box.update()
                if u is not None:
                    boxes[str(sysid)] = u
            return {"type": "update", "seq": self.seq, "now_s": now_s, "station": self._station(), "boxes": boxes}

    def snapshot(self, now_s: float) -> dict:
        """Everything published so far (the rings), consistent with the updates that follow it (`seq`)."""
        with self.lock:
            return {"type": "snapshot", "seq": self.seq, "now_s": now_s, "station": self._station(),
                    "boxes": {str(s): b.snapshot() for s, b in self.boxes.items()}}
