"""systemd's notification protocol (fsw.sd_notify) against a real unix datagram socket standing in for
systemd's: READY once, WATCHDOG=1 every half watchdog period of loop time, STOPPING; abstract names; a
socket that is gone counted, never raised."""
import os
import socket

import pytest

from fsw.sd_notify import Notifier, socket_address


@pytest.fixture
def systemd(tmp_path):
    path = str(tmp_path / "notify")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.setblocking(False)
    yield path, sock
    sock.close()


def received(sock):
    out = []
    while True:
        try:
            out.append(sock.recv(4096).decode())
        except BlockingIOError:
            return out


def test_ready_then_the_watchdog_every_half_period_of_loop_time(systemd):
    path, sock = systemd
    n = Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "2000000", "WATCHDOG_PID": str(os.getpid())})
    assert n.enabled and n.watchdog_s == 2.0
    msgs = []
    for k in range(1001):          # 10 s of a 100 Hz loop; systemd reads as they come (a queue holds ~10)
        n.heartbeat(k / 100)
        msgs += received(sock)
    n.stopping()
    n.close()
    msgs += received(sock)
    assert msgs[0] == "READY=1\nSTATUS=flying"
    assert msgs[1:-1] == ["WATCHDOG=1"] * 11  # at 0, 1, 2 ... 10 s
    assert msgs[-1] == "STOPPING=1\nSTATUS=stopping"
    assert n.send_errors == 0 and n.sent == 13


def test_a_loop_that_stops_ticking_stops_feeding(systemd):
    path, sock = systemd
    n = Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "1000000"})
    n.heartbeat(0.0)
    n.heartbeat(0.6)
    assert received(sock) == ["READY=1\nSTATUS=flying", "WATCHDOG=1", "WATCHDOG=1"]
    assert received(sock) == []    # no tick, no feed: systemd's timer runs out


def test_no_watchdog_for_another_process_or_without_usec(systemd):
    path, sock = systemd
    for env in ({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "1000000", "WATCHDOG_PID": "1"},
                {"NOTIFY_SOCKET": path}, {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "x"}):
        n = Notifier(env)
        n.heartbeat(0.0)
        n.heartbeat(5.0)
        assert received(sock) == ["READY=1\nSTATUS=flying"]


def test_outside_systemd_nothing_happens():
    n = Notifier({})
    assert not n.enabled
    n.heartbeat(0.0)
    n.stopping()
    assert n.sent == 0 and n.send_errors == 0


def test_a_socket_that_is_gone_is_counted_not_raised(tmp_path):
    n = Notifier({"NOTIFY_SOCKET": str(tmp_path / "gone"), "WATCHDOG_USEC": "1000000"})
    n.heartbeat(0.0)
    n.heartbeat(1.0)
    assert n.sent == 0 and n.send_errors >= 2 and not n.ready


def test_abstract_socket_names():
    assert socket_address("@systemd/notify") == b"\0systemd/notify"
    assert socket_address("/run/systemd/notify") == "/run/systemd/notify"
    name = f"debris-box-test-{os.getpid()}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(b"\0" + name.encode())
    try:
        n = Notifier({"NOTIFY_SOCKET": "@" + name})
        n.heartbeat(0.0)
        assert sock.recv(100) == b"READY=1\nSTATUS=flying"
    finally:
        sock.close()
