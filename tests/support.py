"""Helpers shared by the test modules (importable from tests/ and its sub-directories: tests/conftest.py
puts this directory on the path)."""
import socket

from fsw.system import NullLink  # noqa: F401  (the tests' null link is the benchmarks')


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


def exit_status(main, argv) -> int:
    """A tool's exit status from its `main(argv)`, whether it returns it or argparse exits with it."""
    try:
        return main(argv)
    except SystemExit as e:
        return e.code if isinstance(e.code, int) else 1
