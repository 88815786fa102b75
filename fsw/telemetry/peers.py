"""Who is on the other end of a datagram uplink: a bounded table of source addresses and the one
address the box answers.

pymavlink's `udpin` keeps every address that ever sent a datagram and copies every frame it writes to
all of them: strangers receive the box's COMMAND_ACKs, and spoofed source addresses grow the list
without bound. Here:

- the *answer address* is the sender of the last frame that authenticated (a valid signature with the
  mission key; `fsw.telemetry.uplink`). Without a mission key nothing authenticates, and the uplink
  names the sender of the last well-formed frame addressed to the box instead (the only thing it can
  know; every state-changing command is refused then anyway);
- every source is counted in a table of at most `capacity` addresses; when it is full the least
  recently seen address other than the answer address is forgotten (counted in `evicted`). However
  many addresses are spoofed, the table stays at `capacity` and the answer address stays in it.

Time (`now_s`) is the loop's, given by the caller.
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

DEFAULT_CAPACITY = 16


@dataclass
class Peer:
    """What one source address sent (since it entered the table)."""

    datagrams: int = 0
    bytes: int = 0
    authenticated: int = 0  # frames from it that authenticated
    first_s: float = 0.0
    last_s: float = 0.0


class PeerTable:
    def __init__(self, capacity: int = DEFAULT_CAPACITY) -> None:
        if capacity < 2:  # room for the answer address and one other
            raise ValueError(f"peer table capacity must be >= 2, got {capacity}")
        self.capacity = int(capacity)
        self._peers: OrderedDict[object, Peer] = OrderedDict()
        self.answer_address = None
        self.answer_since_s: float | None = None
        self.sources = 0  # addresses entered into the table (again after eviction), since start
        self.evicted = 0

    def __len__(self) -> int:
        return len(self._peers)

    def __contains__(self, addr) -> bool:
        return addr in self._peers

    def get(self, addr) -> Peer | None:
        return self._peers.get(addr)

    def seen(self, addr, size: int, now_s: float) -> Peer:
        """A datagram of `size` bytes from `addr`."""
        p = self._entry(addr, now_s)
        p.datagrams += 1
        p.bytes += size
        p.last_s = now_s
        return p

    def _entry(self, addr, now_s: float) -> Peer:
        p = self._peers.get(addr)
        if p is None:
            if len(self._peers) >= self.capacity:
                self._evict()
            p = self._peers[addr] = Peer(first_s=now_s, last_s=now_s)
            self.sources += 1
        else:
            self._peers.move_to_end(addr)
        return p

    def _evict(self) -> None:
        for old in self._peers:
            if old != self.answer_address:
                del self._peers[old]
                self.evicted += 1
                return

    def answer(self, addr, now_s: float, *, authenticated: bool) -> None:
        """From now on answers go to `addr` (it sent a frame that authenticated, or, without a key,
        a well-formed frame addressed to the box)."""
        if addr != self.answer_address:
            self.answer_address = addr
            self.answer_since_s = now_s
        p = self._entry(addr, now_s)  # normally there already: it just sent the frame
        if authenticated:
            p.authenticated += 1

    def foreign(self, addr) -> bool:
        """Whether `addr` is not the answer address (an unknown or unauthenticated source)."""
        return addr != self.answer_address
