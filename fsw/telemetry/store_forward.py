"""Store and forward: telemetry that cannot go out while the downlink is down waits in a bounded ring
and is sent again, oldest first, when the link returns.

What is kept: the data products, whose loss the ground cannot make up for — magnetometer samples
(DEBRIS_MAG_SAMPLE), rate estimates, simulator truth, inertia estimates (`STORED_IDS`). Status messages
(HEARTBEAT, SYS_STATUS, loop / magnetometer / link status, de-orbit status) describe the present; an old
one is worth nothing, so they are dropped during an outage. Every stored message carries its own
time (time_usec), so the ground merges the replayed ones by time.

Replayed messages are packed again when they finally go out: a fresh sequence number (the ground's
loss count stays a statement about the link) and, when signing, a fresh signing timestamp (the
original one would be refused as a replay).

Link state: a link is *down* after a write that failed (serial port gone, socket error, pymavlink's
serial "port dead" = write returned −1) and is tried again every `retry_s`; the first successful
write brings it back up. UDP has no carrier: a datagram sent to a host nobody listens on is not an
error (Linux reports ICMP port-unreachable only on connected sockets), so over UDP the link is always
"up" and an outage of the receiving side loses what was sent meanwhile. A radio on a serial port
reports an unplugged or powered-down adapter as a write error.

Replay budget: at most `replay_bytes_per_s` of replayed frames per second (token bucket, one second
deep), on top of the live stream: replay never delays live telemetry, and the radio is not
saturated. The ring is preallocated (`capacity` slots); when full, the oldest message is dropped and
counted in `dropped`.
"""
from __future__ import annotations

from .dialect import mavlink

STORED_IDS = frozenset({
    mavlink.MAVLINK_MSG_ID_DEBRIS_MAG_SAMPLE,
    mavlink.MAVLINK_MSG_ID_DEBRIS_RATE_ESTIMATE,
    mavlink.MAVLINK_MSG_ID_DEBRIS_SIM_STATE,
    mavlink.MAVLINK_MSG_ID_DEBRIS_INERTIA_ESTIMATE,
})

DEFAULT_CAPACITY = 8192
DEFAULT_RETRY_S = 1.0
#: about half of a 57,600-baud radio (5,760 B/s)
DEFAULT_REPLAY_BYTES_PER_S = 2500.0


def stored(msg) -> bool:
    """Whether `msg` is kept during an outage."""
    return msg.get_msgId() in STORED_IDS


class FrameRing:
    """A preallocated FIFO of `capacity` messages; pushing into a full ring drops the oldest."""

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError("capacity must be >= 1")
        self._slots: list = [None] * capacity
        self._head = 0  # oldest
        self._n = 0
        self.dropped = 0

    @property
    def capacity(self) -> int:
        return len(self._slots)

    def __len__(self) -> int:
        return self._n

    def push(self, item) -> None:
        cap = len(self._slots)
        if self._n == cap:
            self._slots[self._head] = None
            self._head = (self._head + 1) % cap
            self._n -= 1
            self.dropped += 1
        self._slots[(self._head + self._n) % cap] = item
        self._n += 1

    def peek(self):
        return self._slots[self._head] if self._n else None

    def pop(self):
        if not self._n:
            return None
        item = self._slots[self._head]
        self._slots[self._head] = None
        self._head = (self._head + 1) % len(self._slots)
        self._n -= 1
        return item


class StoreForward:
    """Link state, the ring, and the replay budget; the packing and writing is done by the caller
    (`fsw.telemetry.telemetry.Telemetry`), which reports each write's outcome."""

    def __init__(self, capacity: int = DEFAULT_CAPACITY, *, retry_s: float = DEFAULT_RETRY_S,
                 replay_bytes_per_s: float = DEFAULT_REPLAY_BYTES_PER_S) -> None:
        self.ring = FrameRing(capacity)
        self.retry_s = float(retry_s)
        self.replay_bytes_per_s = float(replay_bytes_per_s)
        self.link_up = True
        self.outages = 0
        self.stored = 0  # messages put in the ring
        self.replayed = 0  # messages sent from the ring
        self.replayed_bytes = 0
        self.skipped = 0  # status messages not kept during an outage
        self.down_since_s: float | None = None
        self._retry_at_s = 0.0
        self._tokens = 0.0
        self._now_s = 0.0

    @property
    def buffered(self) -> int:
        return len(self.ring)

    @property
    def dropped(self) -> int:
        return self.ring.dropped

    def may_send(self) -> bool:
        """Whether a message should be written now: the link is up, or it is down and a retry is due
        (else: keep the message, or skip it)."""
        return self.link_up or self._now_s >= self._retry_at_s

    def keep(self, msg) -> None:
        """A message that could not go out now: into the ring if it is a data product."""
        if stored(msg):
            self.ring.push(msg)
            self.stored += 1
        else:
            self.skipped += 1

    def write_failed(self) -> None:
        if self.link_up:
            self.link_up = False
            self.outages += 1
            self.down_since_s = self._now_s
        self._retry_at_s = self._now_s + self.retry_s

    def write_ok(self) -> None:
        if not self.link_up:
            self.link_up = True
            self.down_since_s = None
            self._tokens = 0.0

    def poll(self, now_s: float) -> None:
        """Once per loop tick, before anything is sent: the time for retries and the replay budget."""
        dt = max(0.0, now_s - self._now_s)
        self._now_s = now_s
        if self.link_up:
            self._tokens = min(self._tokens + dt * self.replay_bytes_per_s, self.replay_bytes_per_s)

    def next_replay(self):
        """The oldest stored message if the link is up and the budget allows, else None."""
        if not self.link_up or not len(self.ring) or self._tokens <= 0.0:
            return None
        return self.ring.peek()

    def replay_sent(self, nbytes: int) -> None:
        self.ring.pop()
        self.replayed += 1
        self.replayed_bytes += nbytes
        self._tokens -= nbytes
