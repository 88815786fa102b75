"""Uplink: the ground's frames, read each loop tick without blocking, verified, then obeyed or refused.

Every byte read goes through a deframer of its own (`fsw.telemetry.framing`: byte-wise resync, no
pymavlink signature check, see `fsw.telemetry.signing`), never through the sending connection's
parser. Per frame:

1. framing and CRC: bytes that do not frame and frames with a bad CRC are counted and dropped;
2. with the mission key loaded, the signature (`signing.Verifier`): unsigned, wrongly signed,
   replayed (timestamp not after the stream's last, or a new stream over a minute old) and
   far-future frames are counted by reason and dropped without an answer (MAVLink signing: an
   unauthenticated frame is ignored). Without a key nothing can be verified: every frame is
   unauthenticated and the router refuses every state-changing command (MAV_RESULT_DENIED).
   Requests that only read are the exception (`UNSIGNED_READS`: PING, TIMESYNC, PARAM_REQUEST_READ,
   PARAM_REQUEST_LIST, MAVLink FTP (always refused), and COMMAND_LONG / COMMAND_INT of a command
   registered as not changing state, e.g. MAV_CMD_REQUEST_MESSAGE): answered unsigned too, at most
   `max_unsigned_per_tick` a tick, so that a ground station without the key sees the box; an
   unsigned state-changing command is still dropped without an answer and counted as unsigned;
3. addressed to us: target system ours or 0, target component ours, 0, or 1 (MAV_COMP_ID_AUTOPILOT1:
   the box is its system's autopilot, and ground stations address a vehicle's commands to
   component 1). COMMAND_LONG → `fsw.commands.CommandRouter` → COMMAND_ACK to the sender (an unknown
   command: MAV_RESULT_UNSUPPORTED); COMMAND_INT the same (param5, param6 = x, y; param7 = z), except
   the commands registered `long_only` (float params 5-6) → MAV_RESULT_COMMAND_LONG_ONLY;
   PARAM_SET → `fsw.commands.ParamTable` (authenticated only) → PARAM_VALUE with the value now in
   force; PARAM_REQUEST_READ / PARAM_REQUEST_LIST → PARAM_VALUE (reading changes nothing);
   the message types given as `handlers` → their handler (which may return an answer, sent like a
   COMMAND_ACK: e.g. TIMESYNC, PING, `fsw.telemetry.services`); anything else is counted and ignored.
   Answers to frames that did not authenticate go out within `answer_limit` (a token bucket, the
   services'): a flood of requests is answered at a bounded rate, the rest counted.

Bounded work, a loop tick at a time, whatever arrives (`poll`; the budgets are arguments of
:class:`Uplink`, sized for 50 Hz on a slow core, far above what a ground station sends):

- a datagram link (:class:`fsw.telemetry.udp_link.UdpLink`, or anything with `read_datagrams`): at
  most `max_datagrams_per_tick` datagrams are taken from the socket, each into a fixed buffer (a
  longer one is dropped whole). They are parsed one datagram at a time (MAVLink over UDP never splits
  a frame): first those from the answer address, then those that are exactly one frame by their
  header, signed if we have the key (every genuine datagram: a sender writes one frame per datagram;
  a flood of 0xFE, 0xFD or random bytes never is), then the rest, while the tick's budgets last —
  `max_parsed_per_tick` datagrams, `max_bytes_per_tick` bytes, `max_crc_checks_per_tick` frame
  candidates. What is over budget is dropped and counted, not left to block later ticks: a signed
  command sent during a flood is obeyed in the tick that reads it;
- a byte stream (serial radio, tcp, an in-memory link with `recv(n)`): at most `max_bytes_per_tick`
  bytes are read (the rest waits in the OS buffer; a radio cannot deliver more), and what is left
  when the CRC budget runs out is dropped and counted;
- a frame's signature is checked on its raw bytes before it is decoded, so forged or unsigned frames
  cost a CRC and a hash, not pymavlink's decoder; at most `max_frames_per_tick` frames are decoded
  (without a key every well-formed frame would be). Noise costs a few ns a byte to parse
  (`fsw.telemetry.framing`).

Every byte is accounted for in :class:`UplinkCounters` and the DEBRIS_LINK_STATUS extension fields
(:meth:`Uplink.link_counters`): bytes received, bytes dropped unparsed, garbage bytes, bad-CRC frames,
datagrams from sources other than the answer address, datagrams the OS dropped.

Answers (COMMAND_ACK, PARAM_VALUE) go to one address only (`fsw.telemetry.peers`): the sender of the
last frame that authenticated; without a key, the sender of the last well-formed frame addressed to
us. Sources are kept in a bounded table (`peers`). When the uplink is the telemetry link itself,
answers go with the telemetry to its configured destination (`reply`).

Nothing raises out of :meth:`Uplink.poll` or :meth:`Uplink.feed`, whatever the bytes: a deframer that
throws would be replaced and the event counted (`parser_resets`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from ..commands import CommandRouter, ParamTable
from .dialect import mavlink
from .framing import Deframer, whole_frame
from .peers import DEFAULT_CAPACITY, PeerTable
from .signing import SigningClock, Verdict, Verifier, setup_outgoing, sign_ready

#: what the flight software's own uplink link id is when it signs its answers on a separate link
UPLINK_LINK_ID = 1
#: message types answered to an unsigned sender although the box has a key (they change nothing;
#: COMMAND_LONG / COMMAND_INT only for commands registered with changes_state=False)
UNSIGNED_READS = frozenset({mavlink.MAVLINK_MSG_ID_PING, mavlink.MAVLINK_MSG_ID_TIMESYNC,
                            mavlink.MAVLINK_MSG_ID_PARAM_REQUEST_READ, mavlink.MAVLINK_MSG_ID_PARAM_REQUEST_LIST,
                            mavlink.MAVLINK_MSG_ID_COMMAND_LONG, mavlink.MAVLINK_MSG_ID_COMMAND_INT,
                            mavlink.MAVLINK_MSG_ID_FILE_TRANSFER_PROTOCOL})
_COMMANDS = ("COMMAND_LONG", "COMMAND_INT")
#: DEBRIS_LINK_STATUS fields filled from the uplink (:meth:`Uplink.link_counters`)
LINK_STATUS_FIELDS = ("cmd_accepted", "rejected_unsigned", "rejected_bad_signature", "rejected_replay",
                      "rejected_invalid", "uplink_bytes", "uplink_bytes_dropped", "uplink_garbage_bytes",
                      "uplink_bad_crc", "uplink_foreign_datagrams", "uplink_os_dropped")


@dataclass
class UplinkCounters:
    bytes: int = 0  # received (datagrams: their true size, dropped ones included)
    frames: int = 0  # intact frames (CRC good)
    garbage_bytes: int = 0  # parsed, not part of a frame (noise)
    bad_crc: int = 0  # runs of one declared frame length whose CRC failed
    datagrams: int = 0
    foreign_datagrams: int = 0  # from a source other than the answer address
    oversize_datagrams: int = 0  # longer than the read buffer: dropped whole
    dropped_datagrams: int = 0  # over the tick's budgets: dropped unparsed (or their rest, unparsed)
    dropped_bytes: int = 0  # bytes not parsed (oversize or over budget) and of frames not decoded
    dropped_frames: int = 0  # intact frames over the tick's decode budget
    os_dropped: int = 0  # datagrams the OS dropped (receive buffer full), as the link reports it
    malformed: int = 0  # intact frames pymavlink could not build
    unsigned: int = 0
    bad_signature: int = 0
    replay: int = 0
    future: int = 0
    not_for_us: int = 0
    ignored: int = 0  # authenticated (or keyless) frames of types we do not act on
    commands: int = 0  # COMMAND_LONG handled (any result)
    params_set: int = 0
    params_refused: int = 0  # PARAM_SET unauthenticated, unknown or out of range
    read_errors: int = 0  # reads that failed, answers that could not be sent
    parser_resets: int = 0
    answers_withheld: int = 0  # answers not sent: the request's sender is not the answer address
    unsigned_reads: int = 0  # unsigned requests that only read, answered (box with a key)
    unsigned_reads_dropped: int = 0  # over the tick's budget for them (counted in `unsigned` too)
    answers_limited: int = 0  # answers to unauthenticated requests over `answer_limit`

    @property
    def rejected_replay(self) -> int:
        return self.replay + self.future


class _LongView:
    """A COMMAND_INT seen as a COMMAND_LONG by the router: param5, param6 = x, y; param7 = z; no
    confirmation (COMMAND_INT has none)."""

    __slots__ = ("command", "param1", "param2", "param3", "param4", "param5", "param6", "param7",
                 "confirmation", "target_system", "target_component", "frame", "_src")

    def __init__(self, msg) -> None:
        self.command = msg.command
        self.param1, self.param2, self.param3, self.param4 = msg.param1, msg.param2, msg.param3, msg.param4
        self.param5, self.param6, self.param7 = float(msg.x), float(msg.y), float(msg.z)
        self.confirmation = 0
        self.target_system, self.target_component, self.frame = msg.target_system, msg.target_component, msg.frame
        self._src = (msg.get_srcSystem(), msg.get_srcComponent())

    def get_srcSystem(self) -> int:
        return self._src[0]

    def get_srcComponent(self) -> int:
        return self._src[1]

    def get_type(self) -> str:
        return "COMMAND_INT"


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
                 max_datagrams_per_tick: int = 128, max_parsed_per_tick: int = 16,
                 max_crc_checks_per_tick: int = 32, max_frames_per_tick: int = 16,
                 peers: int = DEFAULT_CAPACITY, max_future_s: float = 600.0,
                 handlers: dict[str, Callable[[object, float, bool], None]] | None = None,
                 max_unsigned_per_tick: int = 2,
                 answer_limit: Callable[[float, bool], bool] | None = None) -> None:
        """Budgets per `poll` (one loop tick; defaults sized for 50 Hz on a slow core): datagrams read,
        datagrams parsed, bytes parsed (stream links: read), frame candidates CRC-checked, frames
        decoded. A genuine ground station needs one or two of each. `handlers`: message type →
        handler(msg, now_s, authenticated) for the messages addressed to us beyond commands and parameters
        (e.g. DEBRIS_SAMPLE_REQUEST); a handler's return value, when not None, is a message sent back as
        the answer. `max_unsigned_per_tick`: unsigned read-only requests decoded a tick (box with a
        key); `answer_limit(now_s, authenticated) -> bool`: may an answer go out (None: always)."""
        self.conn = conn
        self.max_unsigned_per_tick = int(max_unsigned_per_tick)
        self.answer_limit = answer_limit
        self._unsigned_left: int | None = None
        self._authenticated = False
        self.router = router
        self.params = params if params is not None else ParamTable()
        self.handlers = dict(handlers or {})
        self.sysid = sysid
        self.compid = compid
        self.clock = clock if clock is not None else SigningClock()
        self.verifier = Verifier(key, self.clock, max_future_s=max_future_s) if key is not None else None
        self.max_bytes_per_tick = int(max_bytes_per_tick)
        self.max_datagrams_per_tick = int(max_datagrams_per_tick)
        self.max_parsed_per_tick = int(max_parsed_per_tick)
        self.max_crc_checks_per_tick = int(max_crc_checks_per_tick)
        self.max_frames_per_tick = int(max_frames_per_tick)
        self.counters = UplinkCounters()
        self.peers = PeerTable(peers)
        self.last_authenticated_s: float | None = None
        self._deframer = Deframer(mavlink1=False)
        self._frames_left: int | None = None  # frame budget of the tick being polled (None: no limit)
        self._reply = reply
        self._packer = None
        if reply is None:
            self._packer = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
            if key is not None:
                setup_outgoing(self._packer, key, self.clock, UPLINK_LINK_ID)
        self._key = key
        self._now_s = 0.0
        self._addr = None  # source address of the frame being handled (datagram links)

    # --- input ----------------------------------------------------------------------------------
    def poll(self, now_s: float) -> None:
        """Read what the link has (non-blocking, bounded) and act on it."""
        self._now_s = now_s
        self._frames_left = self.max_frames_per_tick
        self._unsigned_left = self.max_unsigned_per_tick
        try:
            read_datagrams = getattr(self.conn, "read_datagrams", None)
            if read_datagrams is not None:
                self._poll_datagrams(read_datagrams, now_s)
            else:
                self._poll_stream(now_s)
        finally:
            self._frames_left = None
            self._unsigned_left = None

    def _poll_stream(self, now_s: float) -> None:
        recv = getattr(self.conn, "recv", None)
        if recv is None:
            return
        self._deframer.check_budget = self.max_crc_checks_per_tick
        try:
            self._read_stream(recv, now_s)
            if self._deframer.starved:  # out of CRC checks for this tick: the rest is dropped
                self.counters.dropped_bytes += self._deframer.discard()
        finally:
            self._deframer.check_budget = None

    def _read_stream(self, recv, now_s: float) -> None:
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

    def _poll_datagrams(self, read_datagrams, now_s: float) -> None:
        c = self.counters
        try:
            batch = read_datagrams(self.max_datagrams_per_tick)
        except Exception:  # noqa: BLE001 - a closed socket
            c.read_errors += 1
            batch = []
        c.os_dropped = int(getattr(self.conn, "os_dropped", 0) or 0)
        peers = self.peers
        answer = peers.answer_address
        genuine_shape = self._genuine_shape
        tiers: tuple[list, list, list] = ([], [], [])
        for d in batch:
            data, addr, size = d
            c.datagrams += 1
            c.bytes += size
            peers.seen(addr, size, now_s)
            if addr != answer:
                c.foreign_datagrams += 1
            if size > len(data):
                c.oversize_datagrams += 1
                c.dropped_bytes += size
                continue
            tiers[0 if addr == answer else 1 if genuine_shape(data) else 2].append(d)
        df = self._deframer
        df.check_budget = self.max_crc_checks_per_tick
        bytes_left, parses_left = self.max_bytes_per_tick, self.max_parsed_per_tick
        try:
            for tier in tiers:
                for data, addr, size in tier:
                    if parses_left <= 0 or len(data) > bytes_left or self._deframer.starved:
                        c.dropped_datagrams += 1
                        c.dropped_bytes += size
                        continue
                    parses_left -= 1
                    bytes_left -= len(data)
                    self._datagram(data, addr, now_s)
        finally:
            self._deframer.check_budget = None

    def _genuine_shape(self, data: bytes) -> bool:
        """A datagram that is exactly one frame by its header, signed when we have the key (O(1))."""
        return whole_frame(data, False) and (self.verifier is None or bool(data[2] & 0x01))

    def _datagram(self, data: bytes, addr, now_s: float) -> None:
        """One datagram, parsed on its own (no frame spans two datagrams)."""
        df = self._deframer
        try:
            items = df.feed_frames(data, end=True)
            if df.starved:  # out of CRC checks for this tick: the rest is dropped
                left = df.discard()
                self.counters.dropped_bytes += left
                self.counters.dropped_datagrams += 1 if left else 0
        except Exception:  # noqa: BLE001 - hostile bytes that break the deframer: start over
            self.counters.parser_resets += 1
            self._deframer = Deframer(mavlink1=False)
            return
        self._items(items, now_s, addr)

    def feed(self, data: bytes, now_s: float) -> None:
        """Parse `data` (the next bytes of a stream) and handle every frame in it. Never raises."""
        self._now_s = now_s
        self.counters.bytes += len(data)
        try:
            items = self._deframer.feed_frames(data)
        except Exception:  # noqa: BLE001 - hostile bytes that break the deframer: start over
            self.counters.parser_resets += 1
            self._deframer = Deframer(mavlink1=False)
            return
        self._items(items, now_s, None)

    def _items(self, items: list, now_s: float, addr) -> None:
        for item in items:
            try:
                if isinstance(item, bytes):
                    self._raw_frame(item, now_s, addr)
                else:
                    self._bad_data(item)
            except Exception:  # noqa: BLE001 - e.g. a reply that cannot be packed
                self.counters.parser_resets += 1

    def _bad_data(self, msg) -> None:
        c = self.counters
        reason = str(getattr(msg, "reason", ""))
        if reason.startswith("Bad prefix"):
            c.garbage_bytes += len(getattr(msg, "data", b"") or b"")
        elif "CRC" in reason:
            c.bad_crc += 1
        else:
            c.malformed += 1

    def _raw_frame(self, frame: bytes, now_s: float, addr) -> None:
        """An intact frame: within the tick's frame budget, verified on its raw bytes, then decoded."""
        c = self.counters
        c.frames += 1
        authenticated = False
        unsigned_read = False
        if self.verifier is not None:
            verdict = self.verifier.check(frame, now_s)
            if verdict is Verdict.UNSIGNED and (frame[7] | frame[8] << 8 | frame[9] << 16) in UNSIGNED_READS:
                if self._unsigned_left is not None and self._unsigned_left <= 0:
                    c.unsigned += 1  # not answered: counted as any unsigned frame, and why
                    c.unsigned_reads_dropped += 1
                    return
                if self._unsigned_left is not None:
                    self._unsigned_left -= 1
                unsigned_read = True
            elif verdict is not Verdict.OK:
                if verdict is Verdict.UNSIGNED:
                    c.unsigned += 1
                elif verdict is Verdict.BAD_SIGNATURE:
                    c.bad_signature += 1
                elif verdict is Verdict.REPLAY:
                    c.replay += 1
                else:
                    c.future += 1
                return
            else:
                authenticated = True
                self.last_authenticated_s = now_s
                if addr is not None:
                    self._answer_to(addr, now_s, authenticated=True)
        if self._frames_left is not None:  # decoding is the expensive part (~15 µs a frame)
            if self._frames_left <= 0:
                c.dropped_frames += 1
                c.dropped_bytes += len(frame)
                return
            self._frames_left -= 1
        msg = self._deframer.decode(frame)
        if msg.get_type() == "BAD_DATA":
            c.malformed += 1
            return
        if unsigned_read:
            if msg.get_type() in _COMMANDS and self.router.changes_state(msg.command):
                c.unsigned += 1  # a command that acts: refused unsigned, without an answer, as always
                return
            c.unsigned_reads += 1
        self._frame(msg, now_s, authenticated, addr)

    def _answer_to(self, addr, now_s: float, *, authenticated: bool) -> None:
        self.peers.answer(addr, now_s, authenticated=authenticated)
        if hasattr(self.conn, "peer"):
            self.conn.peer = addr  # a udpin link sends its telemetry there too

    def _frame(self, msg, now_s: float, authenticated: bool, addr=None) -> None:
        c = self.counters
        kind = msg.get_type()
        handler = self.handlers.get(kind)
        if handler is not None or kind in ("COMMAND_LONG", "COMMAND_INT", "PARAM_SET", "PARAM_REQUEST_READ",
                                           "PARAM_REQUEST_LIST"):
            if not self._for_us(msg):
                c.not_for_us += 1
                return
            if not authenticated and self.verifier is None and addr is not None:
                self._answer_to(addr, now_s, authenticated=False)  # no key: the last well-formed sender
        self._addr = addr
        self._authenticated = authenticated
        if handler is not None:
            answer = handler(msg, now_s, authenticated)
            if answer is not None:
                self._answer(msg, answer)
        elif kind in _COMMANDS:
            c.commands += 1
            if kind == "COMMAND_INT" and self.router.long_only(msg.command):
                result, param2 = mavlink.MAV_RESULT_COMMAND_LONG_ONLY, 0
            else:
                result = self.router.handle(msg if kind == "COMMAND_LONG" else _LongView(msg), now_s,
                                            authenticated=authenticated)
                param2 = self.router.result_param2
            self._answer(msg, mavlink.MAVLink_command_ack_message(
                msg.command, result, 0, param2, msg.get_srcSystem(), msg.get_srcComponent()))
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
        """Addressed to us (our component or the system's autopilot, component 1), or to everyone (a message
        without target fields, e.g. SYSTEM_TIME)."""
        return getattr(msg, "target_system", 0) in (0, self.sysid) and getattr(msg, "target_component", 0) in (
            0, self.compid, mavlink.MAV_COMP_ID_AUTOPILOT1)

    # --- output ---------------------------------------------------------------------------------
    def _param_value(self, request, name: str) -> None:
        ptype = mavlink.MAV_PARAM_TYPE_INT32 if self.params.is_integer(name) else mavlink.MAV_PARAM_TYPE_REAL32
        names = self.params.names()
        self._answer(request, mavlink.MAVLink_param_value_message(
            name.encode("ascii"), self.params.get(name), ptype, len(names), names.index(name)))

    def _answer(self, request, msg) -> None:
        """To the answer address: the request's sender, which just authenticated (or, without a key,
        sent a well-formed frame to us); on a stream link or with `reply`, along the link. An answer to a
        request that did not authenticate goes out only within `answer_limit`."""
        if self.answer_limit is not None and not self.answer_limit(self._now_s, self._authenticated):
            self.counters.answers_limited += 1
            return
        if self._reply is not None:
            self._reply(msg)
            return
        p = self._packer
        if self._key is not None:
            sign_ready(p, self.clock, self._now_s)
        buf = msg.pack(p)
        p.seq = (p.seq + 1) % 256
        addr = self._addr
        send_to = getattr(self.conn, "send_to", None)
        try:
            if addr is not None and send_to is not None:
                if addr == self.peers.answer_address:
                    send_to(buf, addr)
                else:
                    self.counters.answers_withheld += 1
            else:
                self.conn.write(buf)
        except (OSError, ValueError):
            self.counters.read_errors += 1

    # --- telemetry ------------------------------------------------------------------------------
    def link_counters(self) -> dict:
        """The DEBRIS_LINK_STATUS uplink fields (`LINK_STATUS_FIELDS`)."""
        c, r = self.counters, self.router.counters
        return {"cmd_accepted": r.accepted,
                "rejected_unsigned": c.unsigned + r.unauthenticated,
                "rejected_bad_signature": c.bad_signature,
                "rejected_replay": c.rejected_replay,
                "rejected_invalid": r.unsupported + r.denied + r.failed + c.params_refused,
                "uplink_bytes": c.bytes,
                "uplink_bytes_dropped": c.dropped_bytes,
                "uplink_garbage_bytes": c.garbage_bytes,
                "uplink_bad_crc": c.bad_crc,
                "uplink_foreign_datagrams": c.foreign_datagrams,
                "uplink_os_dropped": c.os_dropped}
