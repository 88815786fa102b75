"""Helpers shared by the test modules (importable from tests/ and its sub-directories: tests/conftest.py
puts this directory on the path)."""
import socket

from fsw.telemetry.dialect import FSW_COMPID, FSW_SYSID, mavlink


def free_udp_port() -> int:
    """A UDP port on the loopback that is free now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_udp_bound(port: int, timeout_s: float = 60.0) -> None:
    """Wait until another process has bound UDP `port` on the loopback (a decoder started in the
    background is listening): binding it ourselves then fails."""
    import errno
    import time

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError as e:
                if e.errno == errno.EADDRINUSE:
                    return
                raise
        time.sleep(0.05)
    raise TimeoutError(f"nothing bound UDP port {port} within {timeout_s:g} s")


class NullLink:
    """A telemetry connection that packs with the flight software's ids, counts bytes and drops them."""

    def __init__(self):
        self.mav = mavlink.MAVLink(self, srcSystem=FSW_SYSID, srcComponent=FSW_COMPID)
        self.bytes = 0

    def write(self, b):
        self.bytes += len(b)


def exit_status(main, argv) -> int:
    """A tool's exit status from its `main(argv)`, whether it returns it or argparse exits with it."""
    try:
        return main(argv)
    except SystemExit as e:
        return e.code if isinstance(e.code, int) else 1
