"""Uplink: the ground's frames, read each loop tick without blocking, verified, then obeyed or refused.

Every byte read goes through a deframer of its own (`fsw.telemetry.framing`: byte-wise resync, no
pymavlink signature check, see `fsw.telemetry.signing`), never through the sending connection's
parser. Per frame:

1. framing and CRC: bytes that do not frame and frames with a bad CRC are counted and dropped;
2. with the mission key loaded, the signature (`signing.Verifier`): unsigned, wrongly signed,
   replayed (timestamp not after the stream's last, or a new stream over a minute old) and
   far-future frames are counted by reason and dropped without an answer (MAVLink signing: an
   unauthenticated frame is ignored). Without a key nothing can be verified: every frame is
   unauthenticated and the router refuses every state-changing command (MAV_RESULT_DENIED);
3. COMMAND_LONG addressed to us (target system / component ours or 0) → `fsw.commands.CommandRouter`
   → COMMAND_ACK to the sender; COMMAND_INT → COMMAND_ACK MAV_RESULT_COMMAND_LONG_ONLY;
   PARAM_SET → `fsw.commands.ParamTable` (authenticated only) → PARAM_VALUE with the value now in
   force; PARAM_REQUEST_READ / PARAM_REQUEST_LIST → PARAM_VALUE (reading changes nothing);
   anything else is counted and ignored.

Bounded work: at most `max_bytes_per_tick` bytes are read per tick (the rest waits in the OS buffer).
Nothing raises out of :meth:`Uplink.poll` or :meth:`Uplink.feed`, whatever the bytes: a deframer that
throws would be replaced and the event counted (`parser_resets`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from ..commands import CommandRouter, ParamTable
from .dialect import mavlink
from .framing import Deframer
from .signing import SigningClock, Verdict, Verifier, setup_outgoing, sign_ready

#: what the flight software's own uplink link id is when it signs its answers on a separate link
UPLINK_LINK_ID = 1


@dataclass
class UplinkCounters:
    bytes: int = 0
    frames: int = 0  # intact frames (CRC good)
    garbage_bytes: int = 0
    bad_crc: int = 0
    malformed: int = 0
    unknown: int = 0  # frames of message ids the dialect lacks
    unsigned: int = 0
    bad_signature: int = 0
    replay: int = 0
    future: int = 0
    not_for_us: int = 0
    ignored: int = 0  # authenticated (or keyless) frames of types we do not act on
    commands: int = 0  # COMMAND_LONG handled (any result)
    params_set: int = 0
    params_refused: int = 0  # PARAM_SET unauthenticated, unknown or out of range
    read_errors: int = 0
    parser_resets: int = 0

    @property
    def rejected_replay(self) -> int:
        return self.replay + self.future


def _param_id(raw) -> str:
    if isinstance(raw, (bytes, bytearray)):
        return bytes(raw).split(b"\x00", 1)[0].decode("ascii", errors="replace")
    return str(raw)


class Uplink:
    """Commands from the ground. `reply(msg) -> bool` sends an answer (COMMAND_ACK, PARAM_VALUE) on the
    link the command came from; when None, the uplink packs and writes answers on `conn` itself."""

    def __init__(self, conn, router: CommandRouter, *, sysid: int, compid: int, key: bytes | None = None,
                 clock: SigningClock | None = None, reply: Callable[[object], bool] | None = None,
                 params: ParamTable | None = None, max_bytes_per_tick: int = 4096,
                 max_future_s: float = 600.0,
                 handlers: dict[str, Callable[[object, float, bool], None]] | None = None) -> None:
        """`handlers`: message type → handler(msg, now_s, authenticated) for the messages addressed to
        us beyond commands and parameters (e.g. DEBRIS_SAMPLE_REQUEST)."""
        self.conn = conn
        self.router = router
        self.params = params if params is not None else ParamTable()
        self.handlers = dict(handlers or {})
        self.sysid = sysid
        self.compid = compid
        self.clock = clock if clock is not None else SigningClock()
        self.verifier = Verifier(key, self.clock, max_future_s=max_future_s) if key is not None else None
        self.max_bytes_per_tick = int(max_bytes_per_tick)
        self.counters = UplinkCounters()
        self.last_authenticated_s: float | None = None
        self._deframer = Deframer()
        self._reply = reply
        self._packer = None
        if reply is None:
            self._packer = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
            if key is not None:
                setup_outgoing(self._packer, key, self.clock, UPLINK_LINK_ID)
        self._key = key
        self._now_s = 0.0

    # --- input ----------------------------------------------------------------------------------
    def poll(self, now_s: float) -> None:
        """Read what the link has (non-blocking, bounded) and act on it."""
        recv = getattr(self.conn, "recv", None)
        if recv is None:
            return
        data = bytearray()
        while len(data) < self.max_bytes_per_tick:
            try:
                chunk = recv(self.max_bytes_per_tick - len(data))
            except Exception:  # noqa: BLE001 - a port that went away, a closed socket
                self.counters.read_errors += 1
                break
            if not chunk:
                break
            data += chunk.encode("latin-1") if isinstance(chunk, str) else chunk
        if data:
            self.feed(bytes(data), now_s)

    def feed(self, data: bytes, now_s: float) -> None:
        """Parse `data` and handle every frame in it. Never raises."""
        self._now_s = now_s
        self.counters.bytes += len(data)
        try:
            msgs = self._deframer.feed(data)
        except Exception:  # noqa: BLE001 - hostile bytes that break the deframer: start over
            self.counters.parser_resets += 1
            self._deframer = Deframer()
            return
        for msg in msgs:
            try:
                self._frame(msg, now_s)
            except Exception:  # noqa: BLE001 - e.g. a reply that cannot be packed
                self.counters.parser_resets += 1

    def _frame(self, msg, now_s: float) -> None:
        c = self.counters
        kind = msg.get_type()
        if kind == "BAD_DATA":
            reason = str(getattr(msg, "reason", ""))
            if reason.startswith("Bad prefix"):
                c.garbage_bytes += len(getattr(msg, "data", b"") or b"")
            elif "CRC" in reason:
                c.bad_crc += 1
            else:
                c.malformed += 1
            return
        if msg.get_msgId() < 0 or kind.startswith("UNKNOWN"):
            c.unknown += 1
            return
        c.frames += 1
        authenticated = False
        if self.verifier is not None:
            verdict = self.verifier.check(bytes(msg.get_msgbuf()), now_s)
            if verdict is not Verdict.OK:
                if verdict is Verdict.UNSIGNED:
                    c.unsigned += 1
                elif verdict is Verdict.BAD_SIGNATURE:
                    c.bad_signature += 1
                elif verdict is Verdict.REPLAY:
                    c.replay += 1
                else:
                    c.future += 1
                return
            authenticated = True
            self.last_authenticated_s = now_s
        handler = self.handlers.get(kind)
        if handler is not None or kind in ("COMMAND_LONG", "COMMAND_INT", "PARAM_SET", "PARAM_REQUEST_READ",
                                           "PARAM_REQUEST_LIST"):
            if not self._for_us(msg):
                c.not_for_us += 1
                return
        if handler is not None:
            handler(msg, now_s, authenticated)
        elif kind == "COMMAND_LONG":
            c.commands += 1
            result = self.router.handle(msg, now_s, authenticated=authenticated)
            self._answer(msg, mavlink.MAVLink_command_ack_message(
                msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))
        elif kind == "COMMAND_INT":
            self._answer(msg, mavlink.MAVLink_command_ack_message(
                msg.command, mavlink.MAV_RESULT_COMMAND_LONG_ONLY, 0, 0, msg.get_srcSystem(),
                msg.get_srcComponent()))
        elif kind == "PARAM_SET":
            name = _param_id(msg.param_id)
            if authenticated and self.params.set(name, float(msg.param_value)):
                c.params_set += 1
            else:
                c.params_refused += 1
            if name in self.params:
                self._param_value(msg, name)
        elif kind == "PARAM_REQUEST_READ":
            names = self.params.names()
            name = _param_id(msg.param_id)
            if not name and 0 <= msg.param_index < len(names):
                name = names[msg.param_index]
            if name in self.params:
                self._param_value(msg, name)
        elif kind == "PARAM_REQUEST_LIST":
            for name in self.params.names():
                self._param_value(msg, name)
        else:
            c.ignored += 1

    def _for_us(self, msg) -> bool:
        return msg.target_system in (0, self.sysid) and msg.target_component in (0, self.compid)

    # --- output ---------------------------------------------------------------------------------
    def _param_value(self, request, name: str) -> None:
        ptype = mavlink.MAV_PARAM_TYPE_INT32 if self.params.is_integer(name) else mavlink.MAV_PARAM_TYPE_REAL32
        names = self.params.names()
        self._answer(request, mavlink.MAVLink_param_value_message(
            name.encode("ascii"), self.params.get(name), ptype, len(names), names.index(name)))

    def _answer(self, request, msg) -> None:
        if self._reply is not None:
            self._reply(msg)
            return
        p = self._packer
        if self._key is not None:
            sign_ready(p, self.clock, self._now_s)
        buf = msg.pack(p)
        p.seq = (p.seq + 1) % 256
        try:
            self.conn.write(buf)
        except (OSError, ValueError):
            self.counters.read_errors += 1

    # --- telemetry ------------------------------------------------------------------------------
    def link_counters(self) -> dict:
        """The DEBRIS_LINK_STATUS uplink fields."""
        c, r = self.counters, self.router.counters
        return {"cmd_accepted": r.accepted,
                "rejected_unsigned": c.unsigned + r.unauthenticated,
                "rejected_bad_signature": c.bad_signature,
                "rejected_replay": c.rejected_replay,
                "rejected_invalid": r.unsupported + r.denied + r.failed + c.params_refused}
