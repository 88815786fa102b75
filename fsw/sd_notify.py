"""systemd's service notification: READY, the watchdog fed by the loop's heartbeat, STOPPING.

Under `Type=notify` systemd gives the service `$NOTIFY_SOCKET`, a unix datagram socket (a path, or an
abstract name written with a leading ``@``); with `WatchdogSec=` it also sets `$WATCHDOG_USEC` (and
`$WATCHDOG_PID`, the process it is meant for). The protocol is one datagram of ``KEY=VALUE`` lines per
notification (sd_notify(3)): ``READY=1`` once the loop runs, ``WATCHDOG=1`` at least once per watchdog
period, ``STOPPING=1`` on the way out, ``STATUS=...`` a line for `systemctl status`.

`Notifier.heartbeat(now_s)` is called after every tick of the loop (`fsw.runner.run_loop`'s
`after_tick`): the first call says READY, then it sends WATCHDOG=1 every half watchdog period, so a loop
that stops ticking (a hang, a deadlock in a driver) stops feeding the watchdog and systemd restarts the
service (`Restart=on-failure`, deploy/debris-box.service). Time is the loop's, injected.

Written here with the standard library rather than with the `sdnotify` package: the protocol is a
single `sendto`, the package's last release is from 2017, and it swallows every failure without a trace,
where this counts them (`send_errors`) — a notification that cannot be sent never stops the loop.
Without `$NOTIFY_SOCKET` (not under systemd, the tests, SITL) every call does nothing.
"""
from __future__ import annotations

import math
import os
import socket
from typing import Mapping


def socket_address(value: str) -> str | bytes:
    """The address of `$NOTIFY_SOCKET`: a path, or an abstract name (``@name`` -> ``b"\\0name"``)."""
    return b"\0" + value[1:].encode() if value.startswith("@") else value


class Notifier:
    """Notifications to systemd from `environ` (default: the process's environment)."""

    def __init__(self, environ: Mapping[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        self.address = socket_address(env["NOTIFY_SOCKET"]) if env.get("NOTIFY_SOCKET") else None
        self.watchdog_s = math.inf
        usec, pid = env.get("WATCHDOG_USEC", ""), env.get("WATCHDOG_PID", "")
        if self.address is not None and usec.isdigit() and int(usec) > 0 and (not pid or pid == str(os.getpid())):
            self.watchdog_s = int(usec) * 1e-6
        self.sent = 0
        self.send_errors = 0
        self.last_error = ""
        self.ready = False
        self._next_feed_s = -math.inf
        self._sock = None
        if self.address is not None:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.setblocking(False)

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    def notify(self, *lines: str) -> bool:
        """Send one datagram of `lines`; False (counted) if it could not be sent."""
        if self._sock is None:
            return False
        try:
            self._sock.sendto("\n".join(lines).encode(), self.address)
        except OSError as error:
            self.send_errors += 1
            self.last_error = str(error)
            return False
        self.sent += 1
        return True

    def heartbeat(self, now_s: float) -> None:
        """After each tick: READY=1 the first time, WATCHDOG=1 every half watchdog period."""
        if self._sock is None:
            return
        if not self.ready:
            self.ready = self.notify("READY=1", "STATUS=flying")
        if now_s >= self._next_feed_s and math.isfinite(self.watchdog_s):
            self.notify("WATCHDOG=1")
            half = self.watchdog_s / 2
            # on a grid of half periods (a tick's lateness does not add up), from now after a long gap
            late = now_s - self._next_feed_s
            self._next_feed_s = self._next_feed_s + half if late <= half else now_s + half

    def stopping(self, status: str = "stopping") -> None:
        self.notify("STOPPING=1", f"STATUS={status}")

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
