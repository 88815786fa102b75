"""Command router: MAVLink COMMAND_LONG (or COMMAND_INT) → a registered handler → MAV_RESULT (→ COMMAND_ACK).

API (everything another module needs)::

    router = CommandRouter()
    router.register(mavlink.MAV_CMD_DEBRIS_CAPSULE, handler, changes_state=True)
    result = router.handle(msg, now_s, authenticated=True)   # → MAV_RESULT_*, never raises

    def handler(msg, now_s: float) -> int:                   # msg: a COMMAND_LONG message
        channel = int_param(msg.param1, 0, 1, "channel")     # raises BadParam → MAV_RESULT_DENIED
        open_ = int_param(msg.param2, 0, 1, "open")
        ...
        return mavlink.MAV_RESULT_ACCEPTED                    # or TEMPORARILY_REJECTED, IN_PROGRESS, …

`msg` has the fields of COMMAND_LONG: ``command``, ``param1`` … ``param7`` (floats), ``confirmation``,
``target_system``, ``target_component``. A handler

- returns a MAV_RESULT value (``None`` counts as ACCEPTED);
- raises :class:`BadParam` (a ``ValueError``) for a parameter out of range → ``MAV_RESULT_DENIED``;
- any other exception is a bug: caught, counted in ``failed``, → ``MAV_RESULT_FAILED``; the loop goes on.

Rules applied before a handler runs (MAVLink command protocol, https://mavlink.io/en/services/command.html):

- unknown command → ``MAV_RESULT_UNSUPPORTED``;
- a state-changing command that did not arrive signed with the mission key (``authenticated=False``,
  e.g. no key loaded on board) → ``MAV_RESULT_DENIED``; commands registered with
  ``changes_state=False`` (requests for information) are answered either way;
- a NaN/inf in a parameter is handed to the handler unchanged (MAVLink uses NaN for "default");
  :func:`int_param` / :func:`float_param` refuse it unless a default is given;
- a retransmission (``confirmation`` > 0) of the command last executed, with identical parameters,
  within :attr:`CommandRouter.retry_window_s`, gets the previous result without running the handler
  again (the ground resends when an ACK was lost; the command must not act twice).

The router does not send anything; the uplink answers each COMMAND_LONG with a COMMAND_ACK carrying
the returned result and :attr:`CommandRouter.result_param2` (0 unless the handler set it with
:meth:`CommandRouter.set_result_param2`, e.g. why a command was refused). It has no dependency on
the link or on signing.

Parameters (PARAM_SET / PARAM_REQUEST_*), same idea::

    params = ParamTable()
    params.register("TLM_SAMPLE_HZ", get, set, lo, hi, integer=False)   # set=None: read-only
    params.set(name, value) -> bool                                      # range-checked, never raises

In the flight software both live on `FlightSoftware`: ``fsw.commands`` and ``fsw.params``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable

from .telemetry.dialect import mavlink

Handler = Callable[[Any, float], "int | None"]

#: results counted as rejections, by name (for telemetry and the soak report)
REJECT_REASONS = ("unsupported", "unauthenticated", "denied", "failed", "temporarily_rejected")


class BadParam(ValueError):
    """A command parameter out of its documented range: the command is refused (MAV_RESULT_DENIED)."""


def int_param(x: float, lo: int, hi: int, name: str, *, default: int | None = None) -> int:
    """A COMMAND_LONG float parameter that must hold an integer in [lo, hi]; NaN → `default` if given."""
    if math.isnan(x) and default is not None:
        return default
    if not math.isfinite(x) or x != round(x) or not lo <= x <= hi:
        raise BadParam(f"{name}={x!r}: must be an integer in [{lo}, {hi}]")
    return int(round(x))


def float_param(x: float, lo: float, hi: float, name: str, *, default: float | None = None) -> float:
    """A COMMAND_LONG float parameter that must be finite and in [lo, hi]; NaN → `default` if given."""
    if math.isnan(x) and default is not None:
        return default
    if not math.isfinite(x) or not lo <= x <= hi:
        raise BadParam(f"{name}={x!r}: must be in [{lo}, {hi}]")
    return float(x)


@dataclass
class _Entry:
    handler: Handler
    changes_state: bool
    long_only: bool = False


@dataclass
class CommandCounters:
    """Commands seen by the router since start."""

    accepted: int = 0
    unsupported: int = 0
    unauthenticated: int = 0
    denied: int = 0
    failed: int = 0
    temporarily_rejected: int = 0
    retries: int = 0  # retransmissions answered from the previous result
    last_error: str = ""
    by_command: dict = field(default_factory=dict)  # command id → number handled

    @property
    def rejected(self) -> int:
        return sum(getattr(self, r) for r in REJECT_REASONS)


def _params(msg) -> tuple:
    return tuple(float(getattr(msg, f"param{i}")) for i in range(1, 8))


def _same_params(a: tuple, b: tuple) -> bool:
    return all(x == y or (math.isnan(x) and math.isnan(y)) for x, y in zip(a, b))


class CommandRouter:
    """Registry of MAV_CMD handlers; :meth:`handle` turns a COMMAND_LONG into a MAV_RESULT."""

    retry_window_s = 10.0

    def __init__(self) -> None:
        self._handlers: dict[int, _Entry] = {}
        self.counters = CommandCounters()
        self._last: tuple | None = None  # (command, params, time, result, result_param2)
        #: COMMAND_ACK.result_param2 of the latest command handled (a handler's detail, e.g. a reason code)
        self.result_param2 = 0
        #: whether the command being handled authenticated (for a handler that answers with messages)
        self.authenticated = True

    def set_result_param2(self, value: int) -> None:
        """For a handler: the COMMAND_ACK's result_param2 (int32) of the command it is handling."""
        self.result_param2 = int(value)

    def register(self, command: int, handler: Handler, *, changes_state: bool = True,
                 long_only: bool = False) -> None:
        """Route `command` (a MAV_CMD value) to `handler`. Registering a command twice is an error.
        `long_only`: its params 5-6 are fractional (COMMAND_INT carries them as integers): COMMAND_INT
        is answered MAV_RESULT_COMMAND_LONG_ONLY."""
        if command in self._handlers:
            raise ValueError(f"command {command} already has a handler")
        self._handlers[int(command)] = _Entry(handler, changes_state, long_only)

    def long_only(self, command: int) -> bool:
        e = self._handlers.get(int(command))
        return e is not None and e.long_only

    def registered(self) -> list[int]:
        return sorted(self._handlers)

    def changes_state(self, command: int) -> bool:
        """Whether `command` needs authentication (unknown commands: True)."""
        e = self._handlers.get(int(command))
        return True if e is None else e.changes_state

    def handle(self, msg, now_s: float, *, authenticated: bool = True) -> int:
        """Run the handler of ``msg.command``; returns the MAV_RESULT for the COMMAND_ACK. Never raises."""
        c = self.counters
        self.result_param2 = 0
        self.authenticated = authenticated
        try:
            command = int(msg.command)
            params = _params(msg)
            confirmation = int(getattr(msg, "confirmation", 0))
        except Exception as e:  # not a COMMAND_LONG at all
            c.failed += 1
            c.last_error = f"malformed command: {e!r}"
            return mavlink.MAV_RESULT_FAILED
        entry = self._handlers.get(command)
        if entry is None:
            c.unsupported += 1
            return mavlink.MAV_RESULT_UNSUPPORTED
        if entry.changes_state and not authenticated:
            c.unauthenticated += 1
            return mavlink.MAV_RESULT_DENIED
        last = self._last
        if (confirmation > 0 and last is not None and last[0] == command and _same_params(last[1], params)
                and 0.0 <= now_s - last[2] <= self.retry_window_s):
            c.retries += 1
            self.result_param2 = last[4]
            return last[3]
        try:
            result = entry.handler(msg, now_s)
            result = mavlink.MAV_RESULT_ACCEPTED if result is None else int(result)
        except BadParam as e:
            c.last_error = f"command {command}: {e}"
            result = mavlink.MAV_RESULT_DENIED
        except Exception as e:  # a handler bug: refused, counted, never into the loop
            c.last_error = f"command {command}: {e!r}"
            c.failed += 1
            self._last = None
            return mavlink.MAV_RESULT_FAILED
        c.by_command[command] = c.by_command.get(command, 0) + 1
        if result in (mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_IN_PROGRESS):
            c.accepted += 1
        elif result == mavlink.MAV_RESULT_DENIED:
            c.denied += 1
        elif result == mavlink.MAV_RESULT_TEMPORARILY_REJECTED:
            c.temporarily_rejected += 1
        elif result == mavlink.MAV_RESULT_UNSUPPORTED:
            c.unsupported += 1
        else:
            c.failed += 1
        self._last = (command, params, now_s, result, self.result_param2)
        return result


# --- parameters (PARAM_SET / PARAM_REQUEST_READ / PARAM_REQUEST_LIST) --------------------------

@dataclass
class _Param:
    name: str
    get: Callable[[], float]
    set: Callable[[float], None] | None
    lo: float
    hi: float
    integer: bool


class ParamTable:
    """Named onboard parameters (MAVLink parameter protocol, https://mavlink.io/en/services/parameter.html).

    ``register(name, get, set, lo, hi, integer=False)``; :meth:`set` validates the range and returns
    whether the value was taken. Names are at most 16 characters. Setting a parameter changes state:
    the uplink allows it only from an authenticated sender.
    """

    def __init__(self) -> None:
        self._params: dict[str, _Param] = {}
        self.rejected = 0

    def register(self, name: str, get: Callable[[], float], set: Callable[[float], None] | None,
                 lo: float, hi: float, *, integer: bool = False) -> None:
        if not 0 < len(name) <= 16 or name in self._params:
            raise ValueError(f"bad or duplicate parameter name {name!r}")
        self._params[name] = _Param(name, get, set, float(lo), float(hi), integer)

    def names(self) -> list[str]:
        return list(self._params)

    def index(self, name: str) -> int:
        return self.names().index(name)

    def __contains__(self, name: str) -> bool:
        return name in self._params

    def get(self, name: str) -> float:
        return float(self._params[name].get())

    def is_integer(self, name: str) -> bool:
        return self._params[name].integer

    def set(self, name: str, value: float) -> bool:
        """Set `name` to `value` if it exists, is writable and `value` is in range; never raises."""
        p = self._params.get(name)
        ok = (p is not None and p.set is not None and math.isfinite(value) and p.lo <= value <= p.hi
              and (not p.integer or value == round(value)))
        if ok:
            try:
                p.set(float(value))
            except Exception:  # a setter bug: refused, never into the loop
                ok = False
        if not ok:
            self.rejected += 1
        return ok
