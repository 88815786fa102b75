"""MAVLink services: the requests stock ground software (MAVProxy, QGroundControl, pymavlink scripts)
sends a MAVLink system, answered by the box.

| request                                        | answer                                 | unsigned, key on board |
|------------------------------------------------|----------------------------------------|------------------------|
| PING (target 0/0)                              | PING to the sender, seq, time mirrored | answered               |
| TIMESYNC (tc1 = 0)                             | TIMESYNC, tc1 = the box's time [ns]    | answered               |
| MAV_CMD_REQUEST_MESSAGE (any message it sends) | ACK + the message                      | answered               |
| MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES (520)   | ACK + AUTOPILOT_VERSION                | answered               |
| MAV_CMD_REQUEST_PROTOCOL_VERSION (519)         | ACK UNSUPPORTED (see below)            | dropped, no answer     |
| MAV_CMD_GET_MESSAGE_INTERVAL (510)             | ACK + MESSAGE_INTERVAL                 | answered               |
| MAV_CMD_SET_MESSAGE_INTERVAL (511)             | ACK; the message's rate changed        | dropped, no answer     |
| PARAM_REQUEST_LIST / PARAM_REQUEST_READ        | PARAM_VALUE (`fsw.telemetry.uplink`)   | answered               |
| FILE_TRANSFER_PROTOCOL (MAVLink FTP)           | NAK UnknownCommand: no files           | answered               |

(`fsw.telemetry.uplink` decides what may be answered unsigned; this module only answers.)

PROTOCOL_VERSION (message 300) is no longer in MAVLink's common set (deprecated in 2025 and removed
from the common.xml pymavlink 2.4.50 ships, which the dialect includes), so the box cannot send it:
MAV_CMD_REQUEST_PROTOCOL_VERSION is answered MAV_RESULT_UNSUPPORTED (the router's answer to any command
it does not know) and REQUEST_MESSAGE of 300 DENIED. That the box speaks MAVLink 2 (only) is in
AUTOPILOT_VERSION's capabilities (MAV_PROTOCOL_CAPABILITY_MAVLINK2) and in every frame it sends.

**Message rates** (:class:`MessageRates`, consulted by `Telemetry` for every message it sends on its
own schedule): MAV_CMD_SET_MESSAGE_INTERVAL with interval -1 turns a message off (not HEARTBEAT: a
box without a heartbeat is lost to every ground station), 0 gives it back its own rate, > 0 µs sends it
at most once per interval, never more often than once per `MIN_INTERVAL_S` (a shorter request is
taken as `MIN_INTERVAL_S`: a request cannot flood the link). The messages the box can make at any
moment (`producers`: HEARTBEAT, SYS_STATUS, SYSTEM_TIME, DEBRIS_LINK_STATUS, DEBRIS_SAMPLE_STORE,
AUTOPILOT_VERSION) are also sent at the requested interval when it is shorter than
their own; the others come with the samples or the applications' events and can only be slowed down
or turned off. DEBRIS_MAG_SAMPLE is refused (DENIED): its samples are numbered and a ground station
asks again for every one missing; its rate is the parameter TLM_SAMPLE_HZ. A requested message
(MAV_CMD_REQUEST_MESSAGE) is sent even when its stream is off.

**Bounded**: answers to requests that did not authenticate (the only ones a stranger can make) are
limited by a token bucket (`answer_rate_hz`, `answer_burst`); what is over it is dropped and counted
(`dropped`), so a flood of requests costs the link a bounded rate. Answers to authenticated requests
are not limited here (the uplink's per-tick decode budget bounds them).
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Callable

from ..commands import int_param
from .dialect import mavlink

#: MAVLink FTP: the header before the data, the payload's size, the opcodes and error used
FTP_HEADER_BYTES = 12
FTP_PAYLOAD_BYTES = 251
FTP_OP_ACK = 128
FTP_OP_NAK = 129
FTP_ERR_UNKNOWN_COMMAND = 7
#: the shortest interval a message can be set to (s): 10 Hz
MIN_INTERVAL_S = 0.1
#: the longest (s): MESSAGE_INTERVAL's int32 µs holds 2147 s
MAX_INTERVAL_S = 2000.0
#: what is true of the box (AUTOPILOT_VERSION.capabilities): MAVLink 2, COMMAND_INT routed like
#: COMMAND_LONG, parameters as floats in PARAM_VALUE (integers C-cast to it)
CAPABILITIES = (mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST)
#: what the box sends (MAV_CMD_REQUEST_MESSAGE / SET_MESSAGE_INTERVAL of any other id: DENIED): the common
#: messages it uses and every dialect message but the ground's request (ids 54000-54099)
BOX_MESSAGES = frozenset(
    {mavlink.MAVLINK_MSG_ID_HEARTBEAT, mavlink.MAVLINK_MSG_ID_SYS_STATUS, mavlink.MAVLINK_MSG_ID_SYSTEM_TIME,
     mavlink.MAVLINK_MSG_ID_STATUSTEXT, mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION,
     mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION}
    | {m for m in mavlink.mavlink_map if 54000 <= m < 54100 and m != mavlink.MAVLINK_MSG_ID_DEBRIS_SAMPLE_REQUEST})
#: messages whose rate SET_MESSAGE_INTERVAL may not change, and why (the COMMAND_ACK's result_param2)
FIXED_RATE = {mavlink.MAVLINK_MSG_ID_DEBRIS_MAG_SAMPLE: 1,  # numbered samples: TLM_SAMPLE_HZ
              mavlink.MAVLINK_MSG_ID_STATUSTEXT: 2}  # events: never decimated
NO_DISABLE = {mavlink.MAVLINK_MSG_ID_HEARTBEAT: 3}


def version_word(version: str) -> int:
    """AUTOPILOT_VERSION.flight_sw_version of "major.minor.patch": major << 24 | minor << 16 | patch << 8 |
    FIRMWARE_VERSION_TYPE (DEV)."""
    parts = [int(p) if p.isdigit() else 0 for p in (version.split(".") + ["0", "0"])[:3]]
    major, minor, patch = (min(max(p, 0), 255) for p in parts)
    return (major << 24) | (minor << 16) | (patch << 8) | mavlink.FIRMWARE_VERSION_TYPE_DEV


class TokenBucket:
    """At most `rate_hz` events a second on average, `burst` at once (loop time, injected)."""

    def __init__(self, rate_hz: float, burst: float) -> None:
        self.rate_hz = float(rate_hz)
        self.burst = float(burst)
        self.tokens = float(burst)
        self._t_s: float | None = None

    def take(self, now_s: float) -> bool:
        if self._t_s is not None and now_s > self._t_s:
            self.tokens = min(self.burst, self.tokens + (now_s - self._t_s) * self.rate_hz)
        self._t_s = now_s if self._t_s is None else max(self._t_s, now_s)
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False


@dataclass
class _Stream:
    interval_s: float  # > 0, or -1.0: off
    next_s: float = -math.inf


class MessageRates:
    """The intervals set by SET_MESSAGE_INTERVAL and when each message was last sent (loop time)."""

    def __init__(self, min_interval_s: float = MIN_INTERVAL_S) -> None:
        self.min_interval_s = float(min_interval_s)
        self.streams: dict[int, _Stream] = {}
        self.last_s: dict[int, float] = {}
        self.previous_s: dict[int, float] = {}
        self.suppressed = 0  # sends skipped: off, or before their interval

    def set(self, msgid: int, interval_s: float) -> float:
        """-1: off; 0: the message's own rate; > 0: at most once per interval (≥ `min_interval_s`).
        Returns the interval now in force (0: own rate)."""
        if interval_s == 0:
            self.streams.pop(msgid, None)
            return 0.0
        if interval_s < 0:
            self.streams[msgid] = _Stream(-1.0)
            return -1.0
        interval_s = min(max(float(interval_s), self.min_interval_s), MAX_INTERVAL_S)
        self.streams[msgid] = _Stream(interval_s)
        return interval_s

    def due(self, msgid: int, now_s: float) -> bool:
        """Whether a message the box is about to send on its own schedule goes out now (recorded if so).
        The slots keep their phase (a message made every 0.999 s still goes every 2nd one at 2 s)."""
        st = self.streams.get(msgid)
        if st is not None:
            if st.interval_s < 0:
                self.suppressed += 1
                return False
            if now_s < st.next_s - 0.25 * st.interval_s:
                self.suppressed += 1
                return False
            st.next_s = st.next_s + st.interval_s if now_s - st.next_s < st.interval_s else now_s + st.interval_s
        self.sent(msgid, now_s)
        return True

    def sent(self, msgid: int, now_s: float) -> None:
        last = self.last_s.get(msgid)
        if last is not None and now_s > last:
            self.previous_s[msgid] = last
        self.last_s[msgid] = now_s

    def faster_than_own(self, msgid: int, now_s: float) -> bool:
        """A message set to an interval whose slot is due now (for the messages the box can make at once)."""
        st = self.streams.get(msgid)
        return st is not None and st.interval_s > 0 and now_s >= st.next_s

    def interval_us(self, msgid: int) -> int:
        """MESSAGE_INTERVAL.interval_us: the interval set, -1 off, else the last interval measured
        between two sends (0: not known yet — not sent twice, or never)."""
        st = self.streams.get(msgid)
        if st is not None:
            return -1 if st.interval_s < 0 else int(round(st.interval_s * 1e6))
        last, prev = self.last_s.get(msgid), self.previous_s.get(msgid)
        if last is None or prev is None:
            return 0
        return min(int(round((last - prev) * 1e6)), 0x7FFFFFFF)


class Services:
    """The answers of the table above. `tlm`: the box's `Telemetry` (its `rates` become this object's
    `rates`); `producers`: message id → fn(now_s) that sends a fresh one (through `tlm`), the flight
    software's (HEARTBEAT, SYS_STATUS, …); `utc_s`: fn(now_s) → the onboard UTC or NaN (for SYSTEM_TIME
    and TIMESYNC), None: not known (the box's loop time is used); `sends`: the ids of every message the
    box sends (REQUEST_MESSAGE of another id is DENIED; one it sends but has not sent yet, e.g. the
    attitude before the filter has one: TEMPORARILY_REJECTED)."""

    def __init__(self, tlm, *, producers: dict[int, Callable[[float], None]] | None = None,
                 utc_s: Callable[[float], float] | None = None, sends: frozenset[int] = BOX_MESSAGES,
                 flight_sw_version: str = "0.0.0", answer_rate_hz: float = 20.0, answer_burst: float = 16.0,
                 min_interval_s: float = MIN_INTERVAL_S) -> None:
        self.tlm = tlm
        self.rates = MessageRates(min_interval_s)
        tlm.rates = self.rates
        self.utc_s = utc_s
        self.flight_sw_version = flight_sw_version
        self.bucket = TokenBucket(answer_rate_hz, answer_burst)
        self.dropped = 0  # answers to unauthenticated requests over the bucket
        self.requests = 0  # requests answered (messages sent for them)
        self.producers: dict[int, Callable[[float], None]] = {
            mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION: lambda now_s: tlm.send(self.autopilot_version()),
            mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: self._system_time,
        }
        self.producers.update(producers or {})
        self.sends = frozenset(sends) | frozenset(self.producers)
        self._router = None

    # --- registration ---------------------------------------------------------------------------------
    def register(self, router) -> None:
        self._router = router
        router.register(mavlink.MAV_CMD_REQUEST_MESSAGE, self.cmd_request_message, changes_state=False)
        router.register(mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
                        self._one_shot(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION), changes_state=False)
        router.register(mavlink.MAV_CMD_GET_MESSAGE_INTERVAL, self.cmd_get_message_interval, changes_state=False)
        router.register(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, self.cmd_set_message_interval, changes_state=True)

    def message_handlers(self) -> dict:
        """PING, TIMESYNC (the time-and-orbit application's TIMESYNC, with the UTC, takes precedence) and
        MAVLink FTP."""
        return {"PING": self.on_ping, "TIMESYNC": self.on_timesync, "FILE_TRANSFER_PROTOCOL": self.on_ftp}

    # --- the bucket -----------------------------------------------------------------------------------
    def allow(self, now_s: float, authenticated: bool) -> bool:
        """May an answer go out now? Authenticated: always; otherwise within the bucket (else counted)."""
        if authenticated or self.bucket.take(now_s):
            return True
        self.dropped += 1
        return False

    # --- commands -------------------------------------------------------------------------------------
    def _send(self, msgid: int, now_s: float) -> int:
        producer = self.producers.get(msgid)
        if producer is not None:
            self.tlm.ungated(producer, now_s)
        else:
            latest = self.tlm.latest.get(msgid)
            if latest is None:  # the box sends it, but has not yet (no attitude before the filter has one)
                return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
            if msgid == mavlink.MAVLINK_MSG_ID_DEBRIS_MAG_SAMPLE:  # a copy: flagged resent
                latest = mavlink.MAVLink_debris_mag_sample_message(
                    latest.time_usec, latest.seq, latest.run_id, latest.mag,
                    (latest.flags | mavlink.DEBRIS_SAMPLE_FLAGS_RESENT) & 0xFF, latest.kit_mag)
            self.tlm.send_now(latest)
        self.requests += 1
        return mavlink.MAV_RESULT_ACCEPTED

    def _allowed(self, now_s: float) -> bool:
        auth = self._router is None or getattr(self._router, "authenticated", True)
        return self.allow(now_s, auth)

    def cmd_request_message(self, msg, now_s: float) -> int:
        """MAV_CMD_REQUEST_MESSAGE: param1 the message id (MESSAGE_INTERVAL: param2 the one asked about);
        the latest instance, or a fresh one for those the box can make at once."""
        mid = int_param(msg.param1, 0, 0xFFFFFF, "message id")
        if mid == mavlink.MAVLINK_MSG_ID_MESSAGE_INTERVAL:
            return self._message_interval(int_param(msg.param2, 0, 0xFFFFFF, "message id"), now_s)
        if mid not in self.sends:
            return mavlink.MAV_RESULT_DENIED
        if not self._allowed(now_s):
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        return self._send(mid, now_s)

    def _one_shot(self, msgid: int):
        def handler(msg, now_s: float) -> int:
            if not self._allowed(now_s):
                return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
            return self._send(msgid, now_s)
        return handler

    def cmd_get_message_interval(self, msg, now_s: float) -> int:
        return self._message_interval(int_param(msg.param1, 0, 0xFFFFFF, "message id"), now_s)

    def _message_interval(self, mid: int, now_s: float) -> int:
        if mid not in self.sends:
            return mavlink.MAV_RESULT_DENIED
        if not self._allowed(now_s):
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        self.tlm.send_now(mavlink.MAVLink_message_interval_message(mid & 0xFFFF, self.rates.interval_us(mid)))
        self.requests += 1
        return mavlink.MAV_RESULT_ACCEPTED

    def cmd_set_message_interval(self, msg, now_s: float) -> int:
        """MAV_CMD_SET_MESSAGE_INTERVAL: param1 message id, param2 interval µs (-1 off, 0 its own rate)."""
        mid = int_param(msg.param1, 0, 0xFFFFFF, "message id")
        interval_us = float(msg.param2)
        if not math.isfinite(interval_us) or (interval_us < 0 and interval_us != -1):
            if self._router is not None:
                self._router.set_result_param2(4)
            return mavlink.MAV_RESULT_DENIED
        reason = FIXED_RATE.get(mid) or (NO_DISABLE.get(mid) if interval_us < 0 else None)
        if mid not in self.sends or reason:
            if reason and self._router is not None:
                self._router.set_result_param2(reason)
            return mavlink.MAV_RESULT_DENIED
        self.rates.set(mid, interval_us * 1e-6 if interval_us > 0 else interval_us)
        return mavlink.MAV_RESULT_ACCEPTED

    # --- messages -------------------------------------------------------------------------------------
    def on_ping(self, msg, now_s: float, authenticated: bool):
        """A PING request (target 0/0) → PING to its sender, time and seq mirrored. A PING addressed to
        us is an answer to a ping we never sent: ignored (two boxes would otherwise ping-pong)."""
        if msg.target_system != 0 or msg.target_component != 0:
            return None
        self.requests += 1
        return mavlink.MAVLink_ping_message(msg.time_usec, msg.seq, msg.get_srcSystem(), msg.get_srcComponent())

    def on_timesync(self, msg, now_s: float, authenticated: bool):
        """TIMESYNC request (tc1 = 0) → tc1 = the box's time [ns] (its UTC when set, else its loop time),
        ts1 mirrored (https://mavlink.io/en/services/timesync.html)."""
        if int(msg.tc1) != 0:
            return None
        self.requests += 1
        utc = self.utc_s(now_s) if self.utc_s is not None else math.nan
        t_s = utc if math.isfinite(utc) else now_s
        return mavlink.MAVLink_timesync_message(int(round(t_s * 1e9)), int(msg.ts1))

    def on_ftp(self, msg, now_s: float, authenticated: bool):
        """MAVLink FTP (https://mavlink.io/en/services/ftp.html): the box serves no files (AUTOPILOT_VERSION
        does not claim MAV_PROTOCOL_CAPABILITY_FTP), but ground stations try it first for the parameters
        (MAVProxy: `@PARAM/param.pck`) and wait for time-outs: every request is answered NAK with
        ERR_UnknownCommand at once, so that they fall back to PARAM_REQUEST_LIST. A reply (ACK/NAK) is
        not answered."""
        raw = bytes(msg.payload)
        if len(raw) < FTP_HEADER_BYTES:
            return None
        seq, session, opcode = struct.unpack_from("<HBB", raw)
        if opcode >= FTP_OP_ACK:
            return None
        self.requests += 1
        nak = struct.pack("<HBBBBBBI", (seq + 1) & 0xFFFF, session, FTP_OP_NAK, 1, opcode, 0, 0, 0) + bytes(
            [FTP_ERR_UNKNOWN_COMMAND])
        return mavlink.MAVLink_file_transfer_protocol_message(
            0, msg.get_srcSystem(), msg.get_srcComponent(), list(nak.ljust(FTP_PAYLOAD_BYTES, b"\0")))

    def _system_time(self, now_s: float) -> None:
        utc = self.utc_s(now_s) if self.utc_s is not None else math.nan
        self.tlm.system_time(now_s, utc)

    def autopilot_version(self):
        zeros8 = [0] * 8
        return mavlink.MAVLink_autopilot_version_message(
            CAPABILITIES, version_word(self.flight_sw_version), 0, 0, 0, zeros8, zeros8, zeros8, 0, 0, 0)

    # --- each tick --------------------------------------------------------------------------------------
    def tick(self, now_s: float) -> None:
        """The messages the box can make at once, set faster than their own rate: sent when their slot is due."""
        for mid in self.rates.streams:
            if mid in self.producers and self.rates.faster_than_own(mid, now_s):
                self.producers[mid](now_s)  # through Telemetry's gate, which records the slot
