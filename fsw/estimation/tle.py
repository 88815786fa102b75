"""Two-line element sets: checked before the box believes one (pure; sgp4 parses and propagates).

:func:`parse_tle` refuses (:class:`TleError` with a `reason`) two lines that are not a TLE: each line
69 characters, line numbers 1 and 2, the same satellite number on both, the modulo-10 checksum of
each line (digits count their value, '-' counts 1, the 69th character is the sum's last digit), and
what sgp4 itself refuses to parse. :func:`check_epoch` refuses an epoch after the given UTC (a TLE from
the future: the onboard time or the TLE is wrong) or older than an age limit (SGP4's error grows by
kilometres a day).

Times are UTC seconds since the Unix epoch.
"""
from __future__ import annotations

from dataclasses import dataclass

#: why a TLE was refused (DEBRIS_TLE_REFUSAL in the dialect mirrors these)
FORMAT, CHECKSUM, FUTURE_EPOCH, TOO_OLD = "format", "checksum", "future epoch", "too old"
TLE_LINE_LEN = 69
_JD_UNIX_EPOCH = 2440587.5


class TleError(ValueError):
    """A TLE refused; `reason` is one of FORMAT, CHECKSUM, FUTURE_EPOCH, TOO_OLD."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class Tle:
    line1: str
    line2: str
    satnum: str
    epoch_utc_s: float

    @property
    def text(self) -> str:
        return f"{self.line1}\n{self.line2}\n"

    def satrec(self):
        from sgp4.api import Satrec
        return Satrec.twoline2rv(self.line1, self.line2)

    def age_s(self, utc_s: float) -> float:
        return utc_s - self.epoch_utc_s


def checksum(line: str) -> int:
    """The modulo-10 checksum of a TLE line's first 68 characters."""
    from sgp4.io import compute_checksum
    return compute_checksum(line)


def parse_tle(line1: str, line2: str) -> Tle:
    """The TLE of two lines (trailing whitespace and line ends ignored), or TleError."""
    lines = []
    for n, raw in ((1, line1), (2, line2)):
        line = str(raw).rstrip("\r\n\x00 ")
        if not line.isascii() or not line.isprintable():
            raise TleError(FORMAT, f"line {n}: not printable ASCII")
        if len(line) != TLE_LINE_LEN:
            raise TleError(FORMAT, f"line {n}: {len(line)} characters, a TLE line has {TLE_LINE_LEN}")
        if line[0] != str(n) or line[1] != " ":
            raise TleError(FORMAT, f"line {n} does not start with '{n} '")
        if not line[68].isdigit():
            raise TleError(FORMAT, f"line {n}: checksum character {line[68]!r} is not a digit")
        if int(line[68]) != checksum(line):
            raise TleError(CHECKSUM, f"line {n}: checksum {line[68]} but the line sums to {checksum(line)}")
        lines.append(line)
    l1, l2 = lines
    if l1[2:7] != l2[2:7]:
        raise TleError(FORMAT, f"satellite numbers differ: {l1[2:7].strip()!r} and {l2[2:7].strip()!r}")
    try:
        from sgp4.io import twoline2rv
        from sgp4.earth_gravity import wgs72
        twoline2rv(l1, l2, wgs72)  # the reference parser's format checks
        from sgp4.api import Satrec
        sat = Satrec.twoline2rv(l1, l2)
    except (ValueError, IndexError) as e:
        raise TleError(FORMAT, f"not a TLE: {str(e).splitlines()[0]}") from None
    if sat.error:
        raise TleError(FORMAT, f"SGP4 cannot initialise from it (error {sat.error})")
    epoch = (sat.jdsatepoch - _JD_UNIX_EPOCH + sat.jdsatepochF) * 86400.0
    return Tle(l1, l2, l1[2:7].strip(), epoch)


def check_epoch(tle: Tle, utc_s: float, max_age_s: float) -> None:
    """TleError unless the epoch is not after `utc_s` and not older than `max_age_s`."""
    age = tle.age_s(utc_s)
    if age < 0:
        raise TleError(FUTURE_EPOCH, f"epoch {-age:.0f} s after the onboard UTC")
    if age > max_age_s:
        raise TleError(TOO_OLD, f"epoch {age / 86400:.2f} days old, the limit is {max_age_s / 86400:g} days")
