"""Send one signed command to the box and wait for its answer.

    python -m ground.command URL --key FILE COMMAND [PARAM ...]    COMMAND_LONG → COMMAND_ACK
    python -m ground.command URL --key FILE --set-param NAME VALUE PARAM_SET → PARAM_VALUE
    python -m ground.command URL [--key FILE] --get-param NAME     PARAM_REQUEST_READ → PARAM_VALUE
    python -m ground.command URL --key FILE time [UTC]              SYSTEM_TIME (the ground's clock, or UTC given)
    python -m ground.command URL --key FILE tle FILE | LINE1 LINE2  DEBRIS_TLE + MAV_CMD_DEBRIS_TLE_LOAD
    python -m ground.command --list                                 the project's commands and their params

COMMAND is a MAV_CMD by name — ``MAV_CMD_DEBRIS_CAPSULE``, ``DEBRIS_CAPSULE`` or ``capsule`` (the
``MAV_CMD_`` and ``MAV_CMD_DEBRIS_`` prefixes may be left out, any case) — or by number. PARAMs are
param1…param7 in order, or ``label=value`` with the labels of the dialect (``channel=0 open=1``);
missing ones are 0, ``nan`` is allowed (MAVLink's "default").

URL: ``udpin:0.0.0.0:14550`` listens for the box's telemetry and answers to its address (the box must
be sending: the first frame from it tells where it is); ``udpout:HOST:PORT`` sends to a box that
listens for commands (`fsw.main --uplink udpin:0.0.0.0:PORT`); a serial device talks over the radio.

``time`` sends SYSTEM_TIME (``time_unix_usec``: the ground's clock, or the ISO 8601 UTC given, e.g.
``2026-05-01T12:00:00Z``), then a TIMESYNC request: the box answers with its UTC, which must match the
time sent within ``TIME_MATCH_S`` (the round trip is printed). ``tle`` checks the two lines first
(69 characters, modulo-10 checksums, one satellite: a bad TLE is a one-line error, exit status 2,
nothing sent), then stages them (DEBRIS_TLE) and loads them with MAV_CMD_DEBRIS_TLE_LOAD carrying
their CRC; a refusal is printed with the box's reason (the COMMAND_ACK's result_param2, a
DEBRIS_TLE_REFUSAL). A FILE may hold a name line before the two lines.

Command protocol (https://mavlink.io/en/services/command.html): without an answer within
``--timeout`` the command is sent again with ``confirmation`` + 1, up to ``--retries`` times; the box
answers a repeat of a command it already ran with the same result without running it twice. With
``--key`` the command is signed and only a correctly signed answer counts. Exit status: 0 accepted
(or in progress), 1 refused (the result is printed), 3 no answer, 2 bad usage.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

from fsw.argtypes import ArgumentParser, check_paths_or_exit, finite_float, int_range, link_url
from fsw.telemetry import dialect
from fsw.telemetry.dialect import FSW_COMPID, FSW_SYSID, GCS_COMPID, GCS_SYSID, mavlink
from fsw.telemetry.framing import Deframer
from fsw.telemetry.signing import SigningClock, Verdict, Verifier, load_key, setup_outgoing, sign_ready

MAV_CMDS: dict[str, int] = {e.name: v for v, e in mavlink.enums["MAV_CMD"].items()
                            if not e.name.endswith("ENUM_END")}
RESULT_NAMES = {v: e.name.removeprefix("MAV_RESULT_") for v, e in mavlink.enums["MAV_RESULT"].items()}


#: the largest magnitude a MAVLink float (IEEE single precision) holds
FLOAT32_MAX = 3.4028234663852886e38
#: MAVLink parameter ids: at most 16 ASCII characters
PARAM_ID_LEN = 16


class UsageError(ValueError):
    pass


def resolve_command(name: str) -> int:
    """MAV_CMD value of a name (with or without the MAV_CMD_ / MAV_CMD_DEBRIS_ prefix) or a number
    (0..65535: COMMAND_LONG's command field is 16 bits)."""
    s = name.strip()
    if s.isdigit():
        if int(s) > 0xFFFF:
            raise UsageError(f"command number {s} is out of range (0..65535)")
        return int(s)
    n = s.upper().replace("-", "_")
    for cand in (n, "MAV_CMD_" + n, "MAV_CMD_DEBRIS_" + n):
        if cand in MAV_CMDS:
            return MAV_CMDS[cand]
    raise UsageError(f"unknown command {name!r} (python -m ground.command --list)")


def parse_params(command: int, items: Sequence[str]) -> list[float]:
    """param1..7 from positional values and/or label=value pairs (labels from the dialect)."""
    entry = mavlink.enums["MAV_CMD"].get(command)
    labels = {str(v).lower().replace(" ", "_"): k for k, v in (getattr(entry, "label", {}) or {}).items()}
    params = [0.0] * 7
    pos = 0
    for item in items:
        if "=" in item:
            key, _, value = item.partition("=")
            key = key.strip().lower().replace(" ", "_")
            if key.startswith("param") and key[5:].isdigit():
                index = int(key[5:])
            elif key in labels:
                index = labels[key]
            else:
                known = ", ".join(sorted(labels)) or "none"
                raise UsageError(f"no parameter {key!r} for this command (labels: {known}; or param1..param7)")
        else:
            pos += 1
            index, value = pos, item
        if not 1 <= index <= 7:
            raise UsageError("at most 7 parameters")
        params[index - 1] = mavlink_float(value, f"parameter {index}")
    return params


def mavlink_float(value: str, what: str) -> float:
    """A value for a MAVLink float field: a number (``nan`` allowed: MAVLink's "default") that a
    float32 holds; UsageError otherwise."""
    try:
        x = float(value)
    except ValueError:
        raise UsageError(f"{what}: not a number: {value!r}") from None
    if math.isinf(x):
        raise UsageError(f"{what}: infinite")
    if abs(x) > FLOAT32_MAX:
        raise UsageError(f"{what}: {value} does not fit a MAVLink float (|x| <= {FLOAT32_MAX:.6g})")
    return x


def param_id(name: str) -> str:
    """An onboard parameter's name as MAVLink carries it: 1..16 ASCII characters; UsageError otherwise."""
    if not name or not name.isascii() or len(name) > PARAM_ID_LEN:
        raise UsageError(f"parameter name {name!r}: must be 1 to {PARAM_ID_LEN} ASCII characters")
    return name


def target_ids(text: str) -> tuple[int, int]:
    """argparse type of --target: SYS/COMP, each 0..255."""
    parts = text.split("/")
    if len(parts) != 2 or not all(p.strip().isdigit() and int(p) <= 255 for p in parts):
        raise argparse.ArgumentTypeError(f"must be SYS/COMP with each 0..255, e.g. {FSW_SYSID}/{FSW_COMPID}; "
                                         f"got {text!r}")
    return int(parts[0]), int(parts[1])


def list_commands() -> str:
    lines = []
    for name, v in sorted(MAV_CMDS.items(), key=lambda kv: kv[1]):
        if not name.startswith("MAV_CMD_DEBRIS_"):
            continue
        e = mavlink.enums["MAV_CMD"][v]
        lines.append(f"{name.removeprefix('MAV_CMD_')} ({v}): {e.description}")
        for i, label in sorted((getattr(e, "label", {}) or {}).items()):
            lines.append(f"    param{i} {label.lower().replace(' ', '_')}: {e.param.get(i, '')}")
    return "\n".join(lines)


@dataclass
class Reply:
    msg: object
    verdict: Verdict | None  # None: no key, nothing verified


@dataclass
class GroundLink:
    """The ground's end of the link, on any byte transport: packs (and signs) what it sends, parses
    and verifies what it receives with its own parser (never pymavlink's signature check)."""

    write: Callable[[bytes], object]
    key: bytes | None = None
    clock: SigningClock = field(default_factory=SigningClock)
    sysid: int = GCS_SYSID
    compid: int = GCS_COMPID
    link_id: int = 0

    def __post_init__(self) -> None:
        self.packer = mavlink.MAVLink(None, srcSystem=self.sysid, srcComponent=self.compid)
        if self.key is not None:
            setup_outgoing(self.packer, self.key, self.clock, self.link_id)
        self.verifier = Verifier(self.key, self.clock) if self.key is not None else None
        self.deframer = Deframer()
        self.rejected = 0

    def send(self, msg, now_s: float) -> bytes:
        if self.key is not None:
            sign_ready(self.packer, self.clock, now_s)
        frame = msg.pack(self.packer)
        self.packer.seq = (self.packer.seq + 1) % 256
        self.write(frame)
        return frame

    def command_long(self, command: int, params: Sequence[float], now_s: float, *,
                     target: tuple[int, int] = (FSW_SYSID, FSW_COMPID), confirmation: int = 0) -> bytes:
        p = list(params) + [0.0] * (7 - len(params))
        return self.send(mavlink.MAVLink_command_long_message(target[0], target[1], command, confirmation, *p), now_s)

    def feed(self, data: bytes, now_s: float) -> list[Reply]:
        """Parse received bytes; intact frames with their verdict (with a key: only OK ones count)."""
        out = []
        for m in self.deframer.feed(data):
            if m.get_msgId() < 0 or m.get_type() == "BAD_DATA":
                continue
            verdict = self.verifier.check(bytes(m.get_msgbuf()), now_s) if self.verifier else None
            if verdict not in (None, Verdict.OK):
                self.rejected += 1
            out.append(Reply(m, verdict))
        return out


def _trusted(r: Reply) -> bool:
    return r.verdict in (None, Verdict.OK)


def _is_from(r: Reply, target: tuple[int, int]) -> bool:
    return (r.msg.get_srcSystem(), r.msg.get_srcComponent()) == tuple(target)


class Session:
    """A ground link over a pymavlink connection, with wall-clock waits (this is the tool's edge)."""

    def __init__(self, url: str, key: bytes | None, *, baud: int = 57600, clock: Callable[[], float] = time.time,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        self.url = url
        self.conn = dialect.open_link(url, source_system=GCS_SYSID, source_component=GCS_COMPID,
                                      input=url.startswith("udpin:"), baud=baud)
        self.listening = url.startswith("udpin:")
        self._clock, self._sleep = clock, sleep
        self.link = GroundLink(self.conn.write, key, SigningClock(clock_set=True, unix_time=clock))
        self.heard = False

    def close(self) -> None:
        self.conn.close()

    def now(self) -> float:
        return self._clock()

    def receive(self) -> list[Reply]:
        data = bytearray()
        for _ in range(64):
            try:
                chunk = self.conn.recv(4096)
            except OSError:
                break
            if not chunk:
                break
            data += chunk.encode("latin-1") if isinstance(chunk, str) else chunk
        return self.link.feed(bytes(data), self.now()) if data else []

    def wait(self, until: Callable[[Reply], bool], timeout_s: float) -> Reply | None:
        end = self.now() + timeout_s
        while self.now() < end:
            for r in self.receive():
                self.heard = True
                if until(r):
                    return r
            self._sleep(0.01)
        return None

    def find_box(self, target: tuple[int, int], timeout_s: float) -> bool:
        """On a listening link: wait for a frame from the box, which tells where to send."""
        if not self.listening or self.heard:
            return True
        return self.wait(lambda r: _is_from(r, target), timeout_s) is not None

    def command(self, command: int, params: Sequence[float], *, target=(FSW_SYSID, FSW_COMPID),
                timeout_s: float = 1.0, retries: int = 3) -> int | None:
        """Send COMMAND_LONG (again with confirmation+1 on silence); the MAV_RESULT, or None."""
        for attempt in range(retries + 1):
            self.link.command_long(command, params, self.now(), target=target, confirmation=attempt)
            r = self.wait(lambda r: _trusted(r) and _is_from(r, target) and r.msg.get_type() == "COMMAND_ACK"
                          and r.msg.command == command, timeout_s)
            if r is not None:
                return int(r.msg.result)
        return None

    def param(self, name: str, value: float | None, *, target=(FSW_SYSID, FSW_COMPID), timeout_s: float = 1.0,
              retries: int = 3) -> float | None:
        """PARAM_SET (value given) or PARAM_REQUEST_READ; the value the box reports, or None."""
        raw = name.encode("ascii")
        for _ in range(retries + 1):
            if value is None:
                msg = mavlink.MAVLink_param_request_read_message(target[0], target[1], raw, -1)
            else:
                msg = mavlink.MAVLink_param_set_message(target[0], target[1], raw, float(value),
                                                        mavlink.MAV_PARAM_TYPE_REAL32)
            self.link.send(msg, self.now())
            r = self.wait(lambda r: _trusted(r) and _is_from(r, target) and r.msg.get_type() == "PARAM_VALUE"
                          and r.msg.param_id == name, timeout_s)
            if r is not None:
                return float(r.msg.param_value)
        return None


#: how close the box's reported UTC must come to the time sent for `time` to count as taken, s
TIME_MATCH_S = 2.0
#: the special COMMANDs
TIME, TLE = "time", "tle"


def parse_utc(text: str) -> float:
    """Unix seconds of an ISO 8601 UTC (a time without a zone is UTC); UsageError otherwise."""
    from datetime import datetime, timezone
    try:
        dt = datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
    except ValueError:
        raise UsageError(f"time {text!r}: not an ISO 8601 UTC such as 2026-05-01T12:00:00Z") from None
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=timezone.utc)
    return dt.timestamp()


def read_tle_args(items: Sequence[str]):
    """The checked TLE of `tle FILE` or `tle LINE1 LINE2` (`fsw.estimation.tle.Tle`); UsageError otherwise."""
    from pathlib import Path

    from fsw.estimation.tle import TleError, parse_tle
    if len(items) == 1:
        try:
            text = Path(items[0]).read_text(encoding="ascii")
        except (OSError, UnicodeDecodeError) as e:
            raise UsageError(f"TLE file {items[0]}: {e}") from None
        lines = [ln.rstrip() for ln in text.splitlines() if ln.strip()]
        lines = [ln for ln in lines if ln[:2] in ("1 ", "2 ")]
        if len(lines) != 2:
            raise UsageError(f"TLE file {items[0]}: {len(lines)} element lines (starting '1 ' or '2 '), need 2")
    elif len(items) == 2:
        lines = list(items)
    else:
        raise UsageError("tle takes a file or the two lines (quoted)")
    try:
        return parse_tle(*lines)
    except TleError as e:
        raise UsageError(f"bad TLE ({e.reason}): {e}") from None


def send_time(s: "Session", utc_s: float | None, *, target=(FSW_SYSID, FSW_COMPID), timeout_s: float = 1.0,
              retries: int = 3) -> tuple[float, float] | None:
    """SYSTEM_TIME (UTC `utc_s`, None: the ground's clock at each send), then TIMESYNC, until the box's
    answer shows the time taken: (the UTC the box reported, the round trip [s]), or None."""
    for _ in range(retries + 1):
        sent_at = s.now()
        utc = sent_at if utc_s is None else utc_s
        s.link.send(mavlink.MAVLink_system_time_message(int(round(utc * 1e6)), 0), sent_at)
        ts1 = int(s.now() * 1e9)
        s.link.send(mavlink.MAVLink_timesync_message(0, ts1), s.now())
        r = s.wait(lambda r, ts1=ts1: _trusted(r) and _is_from(r, target) and r.msg.get_type() == "TIMESYNC"
                   and r.msg.tc1 != 0 and r.msg.ts1 == ts1, timeout_s)
        if r is None:
            continue
        back = s.now()
        expected = utc + (back + ts1 * 1e-9) / 2 - sent_at  # the box answered half a round trip ago
        if abs(r.msg.tc1 * 1e-9 - expected) <= TIME_MATCH_S:
            return r.msg.tc1 * 1e-9, back - ts1 * 1e-9
    return None


def send_tle(s: "Session", tle, *, target=(FSW_SYSID, FSW_COMPID), timeout_s: float = 1.0,
             retries: int = 3) -> tuple[int | None, str]:
    """Stage (DEBRIS_TLE) and load (MAV_CMD_DEBRIS_TLE_LOAD) `tle`: (MAV_RESULT or None, the box's reason)."""
    from fsw.timeorbit import tle_crc
    crc = tle_crc(tle.line1, tle.line2)
    command = mavlink.MAV_CMD_DEBRIS_TLE_LOAD
    for attempt in range(retries + 1):
        s.link.send(mavlink.MAVLink_debris_tle_message(target[0], target[1], tle.line1.encode(),
                                                       tle.line2.encode()), s.now())
        s.link.command_long(command, [float(crc)], s.now(), target=target, confirmation=attempt)
        r = s.wait(lambda r: _trusted(r) and _is_from(r, target) and r.msg.get_type() == "COMMAND_ACK"
                   and r.msg.command == command, timeout_s)
        if r is None:
            continue
        result, code = int(r.msg.result), int(r.msg.result_param2)
        e = mavlink.enums["DEBRIS_TLE_REFUSAL"].get(code) if code else None
        return result, (e.description if e is not None else "")
    return None, ""


def main(argv: list[str] | None = None) -> int:
    ap = ArgumentParser(prog="python -m ground.command", description=__doc__.splitlines()[0],
                                 epilog="Commands: python -m ground.command --list")
    ap.add_argument("url", nargs="?", type=link_url,
                    help="udpin:0.0.0.0:14550, udpout:HOST:PORT, tcp:HOST:PORT or a serial device")
    ap.add_argument("command", nargs="?", help="MAV_CMD name or number")
    ap.add_argument("params", nargs="*", help="param1..param7 in order, or label=value")
    ap.add_argument("--key", metavar="FILE", help="mission key file: sign the command, verify the answer")
    ap.add_argument("--set-param", nargs=2, metavar=("NAME", "VALUE"), help="set an onboard parameter")
    ap.add_argument("--get-param", metavar="NAME", help="read an onboard parameter")
    ap.add_argument("--target", type=target_ids, default=(FSW_SYSID, FSW_COMPID), metavar="SYS/COMP",
                    help=f"target system/component, each 0..255 (default {FSW_SYSID}/{FSW_COMPID})")
    ap.add_argument("--timeout", type=finite_float(0, 3600, min_exclusive=True), default=1.0, metavar="S",
                    help="wait per attempt (default 1 s)")
    ap.add_argument("--retries", type=int_range(0, 100), default=3, help="repeats without an answer (default 3)")
    ap.add_argument("--wait", type=finite_float(0, 3600), default=5.0, metavar="S",
                    help="on a listening link, wait this long for the box to be heard (default 5 s)")
    ap.add_argument("--baud", type=int_range(1), default=57600, help="serial baud rate (default 57600)")
    ap.add_argument("--list", action="store_true", help="list the project's commands and exit")
    args = ap.parse_intermixed_args(argv)
    if args.list:
        print(list_commands())
        return 0
    if args.url is None or (args.command is None and not args.set_param and not args.get_param):
        ap.error("URL and COMMAND (or --set-param / --get-param) are required")
    if sum(x is not None for x in (args.command, args.set_param, args.get_param)) > 1:
        ap.error("give one of COMMAND, --set-param and --get-param (the others would be ignored)")
    check_paths_or_exit(ap, inputs={"--key": args.key})
    target = args.target
    special = args.command.lower() if args.command and args.command.lower() in (TIME, TLE) else None
    try:
        if args.set_param:
            param_id(args.set_param[0])
            set_value = mavlink_float(args.set_param[1], f"--set-param {args.set_param[0]}")
        elif args.get_param:
            param_id(args.get_param)
        elif special == TIME:
            if len(args.params) > 1:
                raise UsageError("time takes at most one argument: the UTC to set (default: this computer's clock)")
            time_utc = parse_utc(args.params[0]) if args.params and args.params[0] != "now" else None
        elif special == TLE:
            tle = read_tle_args(args.params)
        elif args.command is not None:
            command = resolve_command(args.command)
            params = parse_params(command, args.params)
        key = load_key(args.key) if args.key else None
    except (UsageError, ValueError) as e:  # KeyFileError is a ValueError
        print(f"ground.command: {e}", file=sys.stderr)
        return 2
    if key is None:
        print("ground.command: no --key: the command goes out unsigned (a box with a key ignores it, a box "
              "without one refuses every state-changing command)", file=sys.stderr)
    try:
        s = Session(args.url, key, baud=args.baud)
    except (OSError, OverflowError, ValueError) as e:  # pymavlink: ValueError for a URL it cannot parse
        print(f"ground.command: {e}", file=sys.stderr)
        return 1
    try:
        if not s.find_box(target, args.wait):
            print(f"ground.command: nothing heard from {target[0]}/{target[1]} on {args.url} in {args.wait:g} s",
                  file=sys.stderr)
            return 3
        if args.set_param or args.get_param:
            name = args.set_param[0] if args.set_param else args.get_param
            value = s.param(name, set_value if args.set_param else None, target=target,
                            timeout_s=args.timeout, retries=args.retries)
            if value is None:
                print(f"ground.command: no answer for parameter {name}", file=sys.stderr)
                return 3
            asked = f" (asked for {set_value:g}: refused or adjusted by the box)" \
                if args.set_param and value != set_value else ""
            print(f"{name} = {value:g}{asked}")
            return 1 if asked else 0
        if special == TIME:
            got = send_time(s, time_utc, target=target, timeout_s=args.timeout, retries=args.retries)
            if got is None:
                print(f"time: the box did not report the time sent after {args.retries + 1} attempts",
                      file=sys.stderr)
                return 3
            print(f"time: the box reports UTC {_iso(got[0])} (round trip {got[1] * 1e3:.0f} ms)")
            return 0
        if special == TLE:
            result, reason = send_tle(s, tle, target=target, timeout_s=args.timeout, retries=args.retries)
            if result is None:
                print(f"tle: no answer after {args.retries + 1} attempts", file=sys.stderr)
                return 3
            why = f": {reason}" if reason else ""
            print(f"tle: satellite {tle.satnum}, epoch {_iso(tle.epoch_utc_s)}: "
                  f"{RESULT_NAMES.get(result, result)}{why}")
            return 0 if result == mavlink.MAV_RESULT_ACCEPTED else 1
        result = s.command(command, params, target=target, timeout_s=args.timeout, retries=args.retries)
    finally:
        s.close()
    name = [n for n, v in MAV_CMDS.items() if v == command]
    shown = name[0] if name else str(command)
    if result is None:
        print(f"{shown}: no answer after {args.retries + 1} attempts", file=sys.stderr)
        return 3
    print(f"{shown}: {RESULT_NAMES.get(result, result)}")
    return 0 if result in (mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_IN_PROGRESS) else 1


def _iso(utc_s: float) -> str:
    from datetime import datetime, timezone
    return datetime.fromtimestamp(utc_s, timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


if __name__ == "__main__":
    from fsw.startup import exit_with

    exit_with(main)
