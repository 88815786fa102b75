"""Command-line argument types shared by the tools: numbers that are finite and in range, ISO 8601 times, link URLs
whose port exists, the output-path check of `fsw.files` as an argparse error, and the parser every
tool builds (:class:`ArgumentParser`).

Every option that takes a number uses :func:`finite_float` or :func:`int_range`: ``nan``, ``inf`` and
values out of range are refused by argparse itself (exit status 2, ``argument --x: ...``), so that a
typo never runs forever, divides by zero or allocates without bound.
"""
from __future__ import annotations

import argparse
import math
import re
from datetime import datetime
from typing import Callable

from .files import PathError, check_paths

#: pymavlink connection prefixes that take HOST:PORT
_NETWORK_PREFIXES = ("udp:", "udpin:", "udpout:", "udpbcast:", "tcp:", "tcpin:", "mcast:")


def _bound_text(lo: float | None, hi: float | None, lo_open: bool, hi_open: bool) -> str:
    def shown(x: float) -> str:
        return str(x) if isinstance(x, int) else f"{x:g}"

    parts = []
    if lo is not None:
        parts.append(f"{'>' if lo_open else '>='} {shown(lo)}")
    if hi is not None:
        parts.append(f"{'<' if hi_open else '<='} {shown(hi)}")
    return " and ".join(parts)


def finite_float(min: float | None = None, max: float | None = None, *, min_exclusive: bool = False,
                 max_exclusive: bool = False) -> Callable[[str], float]:
    """An argparse `type`: a finite float within [min, max] (bounds open when `*_exclusive`)."""
    bounds = _bound_text(min, max, min_exclusive, max_exclusive)

    def parse(text: str) -> float:
        try:
            x = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
        if not math.isfinite(x):
            raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
        if (min is not None and (x <= min if min_exclusive else x < min)) or \
                (max is not None and (x >= max if max_exclusive else x > max)):
            raise argparse.ArgumentTypeError(f"must be {bounds}, got {text}")
        return x

    parse.__name__ = "number"
    return parse


def int_range(min: int | None = None, max: int | None = None) -> Callable[[str], int]:
    """An argparse `type`: an integer (decimal digits) within [min, max]."""
    bounds = _bound_text(min, max, False, False)

    def parse(text: str) -> int:
        try:
            x = int(text.strip())
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
        if (min is not None and x < min) or (max is not None and x > max):
            raise argparse.ArgumentTypeError(f"must be {bounds}, got {text}")
        return x

    parse.__name__ = "integer"
    return parse


def link_url(text: str) -> str:
    """An argparse `type` for a pymavlink connection string: a network one (``udpin:``, ``udpout:``,
    ``tcp:`` ...) needs HOST:PORT with a port in 1..65535; anything else (a serial device, a file)
    passes unchanged, for the tool that opens it to judge."""
    if not text.strip():
        raise argparse.ArgumentTypeError("empty: give a connection string or a device")
    lower = text.lower()
    prefix = next((p for p in _NETWORK_PREFIXES if lower.startswith(p)), None)
    if prefix is None:
        return text
    m = re.fullmatch(r"(.*):([^:]*)", text[len(prefix):])
    if m is None or not m.group(1):
        raise argparse.ArgumentTypeError(f"{text!r}: expected {prefix}HOST:PORT")
    port = m.group(2)
    if not port.isdigit() or not 1 <= int(port) <= 65535:
        raise argparse.ArgumentTypeError(f"{text!r}: port must be a number in 1..65535, got {port!r}")
    return text


class ArgumentParser(argparse.ArgumentParser):
    """argparse's parser, except that ``--option=--`` gives the option the value ``--`` (for its type to
    judge). Python 3.11's argparse drops a ``--`` wherever it appears, so that the option got an empty
    list: no type check, and a TypeError deep in the tool (``--rate=--``)."""

    def _get_values(self, action, arg_strings):
        if action.option_strings and action.nargs is None and arg_strings == ["--"]:
            value = self._get_value(action, "--")
            self._check_value(action, value)
            return value
        return super()._get_values(action, arg_strings)


def iso_time(text: str) -> datetime:
    """argparse type of --utc0: an ISO 8601 date and time."""
    try:
        return datetime.fromisoformat(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an ISO 8601 time: {text!r} (e.g. 2025-06-15T12:00:00)") from None


def check_paths_or_exit(ap: argparse.ArgumentParser, inputs=(), outputs=()) -> None:
    """`fsw.files.check_paths` as a usage error: one line on stderr, exit status 2."""
    try:
        check_paths(inputs=inputs, outputs=outputs)
    except PathError as e:
        ap.error(str(e))
