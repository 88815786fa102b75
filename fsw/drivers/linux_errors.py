"""What a failed Linux I2C/SPI transfer was, from its errno: the buses count each kind.

The kernel's I2C adapters report a device that does not acknowledge as EREMOTEIO or ENXIO
(Documentation/i2c/fault-codes.rst), a bus that does not complete in time (clock stretching, a line
held low) as ETIMEDOUT, and anything else (EIO above all: lost arbitration, a controller error) as a
plain I/O error.
"""
from __future__ import annotations

import errno

NACK_ERRNOS = frozenset({errno.EREMOTEIO, errno.ENXIO})
TIMEOUT_ERRNOS = frozenset({errno.ETIMEDOUT})


class TransferCounters:
    """Failed transfers of one bus by kind: `nacks`, `timeouts`, `io_errors`."""

    def __init__(self) -> None:
        self.nacks = 0
        self.timeouts = 0
        self.io_errors = 0

    def count(self, error: OSError) -> str:
        """Count `error` under its kind; return the kind's name for the error message."""
        if error.errno in NACK_ERRNOS:
            self.nacks += 1
            return "NACK"
        if error.errno in TIMEOUT_ERRNOS:
            self.timeouts += 1
            return "timeout"
        self.io_errors += 1
        return "I/O error"
