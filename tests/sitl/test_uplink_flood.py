"""Floods and strangers on the uplink and on the ground decoder's port: the deframer's cost bound
(CRCs counted, not timed), the uplink's per-tick budgets, the flight loop in SITL lockstep under a
1 MB/s flood over a real UDP socket, the ground decoder under the same flood, and who gets answers."""
import socket
import threading
import time
from collections import deque

import numpy as np
import pytest

from fsw.commands import CommandRouter
from fsw.flight import FlightSoftware
from fsw.telemetry import framing
from fsw.telemetry.dialect import FSW_COMPID, FSW_SYSID, mavlink
from fsw.telemetry.framing import Deframer
from fsw.telemetry.peers import PeerTable
from fsw.telemetry.signing import SigningClock, Verdict, sign_frame, unix_to_timestamp
from fsw.telemetry.telemetry import Telemetry
from fsw.telemetry.udp_link import UdpLink
from fsw.telemetry.uplink import Uplink
from ground.command import GroundLink
from ground.decode import run as decode_run
from support import free_udp_port

KEY = bytes(range(50, 82))
T0 = unix_to_timestamp(1_750_000_000.0)
R = mavlink
RNG = np.random.default_rng(7)
N_FLOOD = 256 * 1024
FLOODS = {"0xFE": b"\xfe" * N_FLOOD, "0xFD": b"\xfd" * N_FLOOD,
          "random": RNG.integers(0, 256, N_FLOOD, dtype=np.uint8).tobytes()}
#: headers that pass every cheap check (HEARTBEAT, payload 1 byte), one every 5 bytes: each needs a CRC
CRAFTED = bytes([0xFD, 1, 0, 0, 0]) * 20_000


def count_crcs(monkeypatch) -> list[int]:
    """Count the deframer's CRC evaluations (whatever its CRC helper is called)."""
    calls = [0]
    name = "crc_x25" if hasattr(framing, "crc_x25") else "_x25"
    orig = getattr(framing, name)

    def counting(*args):
        calls[0] += 1
        return orig(*args)

    monkeypatch.setattr(framing, name, counting)
    return calls


def deframe(d: Deframer, data: bytes, chunk: int = 4096) -> list:
    out = []
    for i in range(0, len(data), chunk):
        out += d.feed(data[i:i + chunk])
    return out + d.flush()


# --- the deframer's cost --------------------------------------------------------------------------
@pytest.mark.parametrize("kind", FLOODS)
@pytest.mark.parametrize("mavlink1", [False, True])
def test_a_flood_costs_the_deframer_no_crc(kind, mavlink1, monkeypatch):
    """256 KB of 0xFE, 0xFD or random bytes: no candidate passes the header checks, so no CRC is
    computed (byte by byte there was one at nearly every 0xFE, ~7 us a byte); every byte is reported."""
    calls = count_crcs(monkeypatch)
    kw = {"mavlink1": True} if mavlink1 else {}
    out = deframe(Deframer(**kw), FLOODS[kind])
    assert all(m.get_type() == "BAD_DATA" for m in out)
    assert sum(len(m.get_msgbuf()) for m in out) == N_FLOOD
    assert calls[0] <= N_FLOOD // 65536  # random bytes: a valid-looking header is a 1e-10 event


def test_crafted_headers_cost_one_crc_each_and_a_budget_bounds_them(monkeypatch):
    calls = count_crcs(monkeypatch)
    out = deframe(Deframer(), CRAFTED)
    assert calls[0] <= len(CRAFTED) // 5
    assert sum(len(m.get_msgbuf()) for m in out) == len(CRAFTED)
    # with a budget the deframer stops where it is; the rest is discarded and counted by the caller
    d = Deframer()
    d.check_budget = 7
    out = d.feed_frames(CRAFTED)
    assert d.starved and d.crc_checks == 7
    parsed = sum(len(m.get_msgbuf()) for m in out + d.flush_frames())
    assert parsed + d.discard() == len(CRAFTED)


def test_genuine_frames_in_a_flood_are_all_found():
    p = mavlink.MAVLink(None, srcSystem=FSW_SYSID, srcComponent=FSW_COMPID)
    frames = []
    for k in range(20):
        frames.append(mavlink.MAVLink_highres_imu_message(k, 0, 0, 0, 0, 0, 0, 0.1, 0.2, 0.3, 0, 0, 0, 0,
                                                          0x1C0).pack(p))
        p.seq = (p.seq + 1) % 256
    stream = b"".join(FLOODS["0xFD"][:3000 + 7 * k] + CRAFTED[:500] + f for k, f in enumerate(frames))
    out = [m for m in deframe(Deframer(), stream, chunk=1000) if m.get_type() != "BAD_DATA"]
    assert [m.time_usec for m in out] == list(range(20))


# --- the uplink's budgets, on an in-memory datagram link ---------------------------------------------
GROUND_ADDR, STRANGER_ADDR = ("10.0.0.1", 14550), ("10.6.6.6", 4444)


class DatagramLink:
    """Datagrams queued by the test, read like `UdpLink.read_datagrams`; answers recorded."""

    def __init__(self):
        self.queue: deque = deque()
        self.sent: list = []
        self.peer = None

    def put(self, data: bytes, addr=STRANGER_ADDR) -> None:
        self.queue.append((bytes(data), addr, len(data)))

    def read_datagrams(self, n: int) -> list:
        return [self.queue.popleft() for _ in range(min(n, len(self.queue)))]

    def send_to(self, buf: bytes, addr) -> None:
        self.sent.append((addr, buf))


def make_uplink(conn, key=KEY):
    router = CommandRouter()
    runs = []
    router.register(R.MAV_CMD_USER_1, lambda m, t: runs.append((m.param1, t)))
    up = Uplink(conn, router, sysid=FSW_SYSID, compid=FSW_COMPID, key=key,
                clock=SigningClock(epoch=T0, clock_set=True))
    return up, runs


def flood_datagrams(kind: str, n_bytes: int = 20_000) -> list[bytes]:
    """One 50 Hz tick of a 1 MB/s flood."""
    if kind == "0xFD 4K":
        return [b"\xfd" * 4000] * (n_bytes // 4000)
    if kind == "random 200B":
        return [RNG.integers(0, 256, 200, dtype=np.uint8).tobytes() for _ in range(n_bytes // 200)]
    if kind == "crafted 1K":
        return [CRAFTED[:1000]] * (n_bytes // 1000)
    if kind == "unsigned frames":  # well-formed (good CRC) unsigned commands, 44 bytes each
        p = mavlink.MAVLink(None, srcSystem=GROUND_ADDR[1] % 255, srcComponent=1)
        f = mavlink.MAVLink_command_long_message(FSW_SYSID, FSW_COMPID, R.MAV_CMD_USER_1, 0, *[9.0] * 7).pack(p)
        return [f] * min(100, n_bytes // len(f))
    raise ValueError(kind)


@pytest.mark.parametrize("kind", ["0xFD 4K", "random 200B", "crafted 1K", "unsigned frames"])
def test_a_signed_command_is_obeyed_in_the_tick_it_arrives_during_a_flood(kind, monkeypatch):
    link = DatagramLink()
    up, runs = make_uplink(link)
    decodes = [0]
    decode = up._deframer.decode

    def counting_decode(frame):
        decodes[0] += 1
        return decode(frame)

    monkeypatch.setattr(up._deframer, "decode", counting_decode)
    ground = GroundLink(lambda b: link.put(b, GROUND_ADDR), KEY, SigningClock(epoch=T0, clock_set=True))
    sent = 0
    for k in range(30):
        flood = flood_datagrams(kind)
        for i, d in enumerate(flood):
            link.put(d)
            sent += len(d)
            if k in (10, 20) and i == len(flood) // 2:
                sent += len(ground.command_long(R.MAV_CMD_USER_1, [k], k * 0.02))
        checks, decodes[0] = up._deframer.crc_checks, 0
        up.poll(k * 0.02)
        assert up._deframer.crc_checks - checks <= up.max_crc_checks_per_tick
        assert decodes[0] <= up.max_frames_per_tick
        assert not link.queue  # nothing left to hold up the next tick
        if k in (10, 20):
            assert runs[-1] == (k, k * 0.02)  # obeyed in this very tick
    assert [r[0] for r in runs] == [10, 20]
    # acknowledged to the ground only
    assert [a for a, _ in link.sent] == [GROUND_ADDR, GROUND_ADDR]
    c = up.counters
    assert c.bytes == sent and c.dropped_bytes > 0
    u = up.link_counters()
    assert u["uplink_bytes"] == sent and u["uplink_bytes_dropped"] == c.dropped_bytes
    assert u["uplink_foreign_datagrams"] >= 30 * len(flood_datagrams(kind)) - 1
    if kind != "unsigned frames":
        assert u["uplink_garbage_bytes"] > 0
    else:
        assert c.unsigned > 0


def test_oversize_datagrams_are_dropped_whole_and_counted():
    link = DatagramLink()
    up, _ = make_uplink(link)
    link.queue.append((b"\xfe" * 2048, STRANGER_ADDR, 65000))
    up.poll(0.0)
    c = up.counters
    assert (c.bytes, c.oversize_datagrams, c.dropped_bytes, c.garbage_bytes) == (65000, 1, 65000, 0)


# --- the flight loop under a flood, SITL lockstep, real UDP -----------------------------------------
class CaptureLink:
    """Telemetry out, kept as bytes."""

    def __init__(self):
        self.mav = mavlink.MAVLink(self, srcSystem=FSW_SYSID, srcComponent=FSW_COMPID)
        self.data = bytearray()

    def write(self, b):
        self.data += b


def sitl_flood_ticks(kind: str, k: int) -> list[bytes]:
    """Tick k's share of a 1 MB/s flood (20 KB at 50 Hz)."""
    if kind == "0xFE 64K":  # 64 KB datagrams of 0xFE, one every 64 ms
        return [b"\xfe" * 65000] if k % 3 == 0 else []
    if kind == "0xFD 4K":
        return [b"\xfd" * 4000] * 5
    if kind == "random 4K":
        return [RNG.integers(0, 256, 4000, dtype=np.uint8).tobytes() for _ in range(5)]
    return [RNG.integers(0, 256, 200, dtype=np.uint8).tobytes() for _ in range(100)]


@pytest.mark.sitl
def test_the_flight_loop_under_a_1MBps_flood_over_udp():
    """50 Hz lockstep for 12 s of loop time; before every tick the tick's 20 KB of flood arrive on the
    uplink's UDP socket (0xFE in 64 KB datagrams, 0xFD and random in 4 KB, random in 200 B, 3 s each);
    in the middle of each flood a genuine signed command. No overrun, each command obeyed within 1 s
    of loop time, the flood counted in DEBRIS_LINK_STATUS."""
    from fsw.config import RunConfig
    from hil import sitl

    uplink = UdpLink("udpin:127.0.0.1:0", source_system=FSW_SYSID, source_component=FSW_COMPID)
    addr = uplink.sock.getsockname()
    box = sitl.build(sitl.SitlConfig(RunConfig(rate_hz=50.0, buffer_frames=0)), link=CaptureLink(), uplink=uplink,
                     key=KEY, clock=SigningClock(epoch=T0, clock_set=True), ident=False)
    sim, fsw, tlm = box.sim, box.fsw, box.flight.tlm
    # the loop's work in this process's CPU time: a test running beside this one is not an overrun
    fsw.scheduler.work_timer = time.thread_time
    executed = []
    fsw.commands.register(R.MAV_CMD_USER_1, lambda m, t: executed.append((m.param1, t)))
    flooder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    gsock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    gsock.setblocking(False)
    ground = GroundLink(lambda b: gsock.sendto(b, addr), KEY, SigningClock(epoch=T0, clock_set=True))
    kinds = ["0xFE 64K", "0xFD 4K", "random 4K", "random 200B"]
    sent, flood_bytes = {}, 0
    try:
        for k in range(600):
            t = k * 0.02
            kind = kinds[min(k // 150, 3)]
            burst = sitl_flood_ticks(kind, k)
            for i, d in enumerate(burst):
                flooder.sendto(d, addr)
                flood_bytes += len(d)
                if k % 150 == 75 and i == len(burst) // 2:
                    ground.command_long(R.MAV_CMD_USER_1, [k], t)
                    sent[k] = t
            if k % 150 == 75 and not burst:
                ground.command_long(R.MAV_CMD_USER_1, [k], t)
                sent[k] = t
            sim.advance_to(t)
            fsw.tick(t)
        acks = GroundLink(lambda b: None, KEY, SigningClock(epoch=T0, clock_set=True))
        replies = acks.feed(b"".join(received(gsock)), 12.0)
    finally:
        flooder.close()
        gsock.close()
        uplink.close()
    st = fsw.scheduler.stats
    assert st.ticks == 600 and st.overruns == 0
    assert sorted(sent) == [75, 225, 375, 525]
    assert [p for p, _ in executed] == sorted(sent)
    assert all(t_exec - sent[int(p)] <= 1.0 for p, t_exec in executed)
    assert [(r.msg.get_type(), r.msg.result, r.verdict) for r in replies] == \
        [("COMMAND_ACK", R.MAV_RESULT_ACCEPTED, Verdict.OK)] * 4
    c = fsw.uplink.counters
    assert c.bytes >= flood_bytes and c.dropped_bytes > 0 and c.garbage_bytes > 0
    status = [m for m in Deframer().feed(bytes(tlm.conn.data)) if m.get_type() == "DEBRIS_LINK_STATUS"][-1]
    assert status.uplink_bytes >= 0.9 * flood_bytes and status.uplink_bytes_dropped > 0
    assert status.uplink_garbage_bytes > 0 and status.uplink_foreign_datagrams > 0
    assert status.cmd_accepted == 4


# --- the ground decoder's live port ---------------------------------------------------------------
def test_the_ground_decoder_loses_no_sample_under_a_1MBps_flood():
    """200 magnetometer samples at 100 Hz from the box's port, and from another port 1 MB/s of 0xFE in
    64 KB datagrams, 0xFD in 4 KB and random bytes in 1 KB datagrams: all 200 decoded."""
    port = free_udp_port()
    addr = ("127.0.0.1", port)
    stop = threading.Event()
    started = threading.Event()

    def box() -> None:
        p = mavlink.MAVLink(None, srcSystem=FSW_SYSID, srcComponent=FSW_COMPID)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            started.wait(5.0)
            time.sleep(0.3)
            t0 = time.monotonic()
            for k in range(200):
                tx.sendto(mavlink.MAVLink_highres_imu_message(10_000 * k, 0, 0, 0, 0, 0, 0, 0.2, -0.1, 0.4,
                                                              0, 0, 0, 0, 0x1C0).pack(p), addr)
                p.seq = (p.seq + 1) % 256
                time.sleep(max(0.0, t0 + 0.01 * (k + 1) - time.monotonic()))

    def flood() -> None:
        rng = np.random.default_rng(3)
        kinds = [b"\xfe" * 65000, b"\xfd" * 4000, None]
        sent = 0
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            started.wait(5.0)
            t0 = time.monotonic()
            while not stop.is_set():
                elapsed = time.monotonic() - t0
                if sent < 1e6 * elapsed:
                    d = kinds[int(elapsed) % 3]
                    d = d if d is not None else rng.integers(0, 256, 1000, dtype=np.uint8).tobytes()
                    tx.sendto(d, addr)
                    sent += len(d)
                else:
                    time.sleep(0.002)

    threads = [threading.Thread(target=f, daemon=True) for f in (box, flood)]
    for th in threads:
        th.start()

    def clock():
        started.set()
        return time.time()

    try:
        dec = decode_run(f"udpin:127.0.0.1:{port}", duration_s=3.5, quiet=True, clock=clock)
    finally:
        stop.set()
        for th in threads:
            th.join(5.0)
    assert len(dec.recording()) == 200
    assert dec.stats.summary()["garbage_bytes"] > 1e6


# --- who gets answers --------------------------------------------------------------------------------
def udp_socket() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.setblocking(False)
    return s


def received(s: socket.socket) -> list[bytes]:
    """What arrived on `s` (loopback delivers during the sender's sendto: nothing is on its way)."""
    out = []
    while True:
        try:
            out.append(s.recv(65536))
        except BlockingIOError:
            return out


def test_answers_go_only_to_the_authenticated_ground_address_and_the_peer_table_is_bounded():
    link = UdpLink("udpin:127.0.0.1:0", source_system=FSW_SYSID, source_component=FSW_COMPID)
    box = link.sock.getsockname()
    up, runs = make_uplink(link)
    a, b = udp_socket(), udp_socket()
    ground = GroundLink(lambda f: a.sendto(f, box), KEY, SigningClock(epoch=T0, clock_set=True))
    stranger = GroundLink(lambda f: b.sendto(f, box), None)
    forger = GroundLink(lambda f: b.sendto(f, box), bytes(32), SigningClock(epoch=T0, clock_set=True))
    try:
        # strangers first: garbage, an unsigned command, a wrongly signed one → no answer to anyone
        b.sendto(b"\xfd" * 300, box)
        stranger.command_long(R.MAV_CMD_USER_1, [1], 0.0)
        forger.command_long(R.MAV_CMD_USER_1, [2], 0.0)
        up.poll(0.0)
        assert received(a) == [] and received(b) == [] and up.peers.answer_address is None
        frame = ground.command_long(R.MAV_CMD_USER_1, [3], 0.02)
        up.poll(0.02)
        b.sendto(frame, box)  # a stranger replays the genuine frame from its own address
        stranger.command_long(R.MAV_CMD_REQUEST_MESSAGE, [0], 0.04)
        up.poll(0.04)
        assert runs == [(3, 0.02)] and up.counters.replay == 1 and up.counters.unsigned == 2
        assert up.peers.answer_address == a.getsockname()
        acks = ground.feed(b"".join(received(a)), 0.05)
        assert [(r.msg.get_type(), r.msg.command, r.verdict) for r in acks] == \
            [("COMMAND_ACK", R.MAV_CMD_USER_1, Verdict.OK)]
        assert received(b) == []
        # 300 spoofed sources: the table stays bounded, the ground's address stays in it
        for i in range(300):
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                s.sendto(bytes([0xFD, 1, 0]) + bytes(i % 200), box)
            if i % 60 == 59:
                up.poll(0.1 + i * 1e-3)
        assert len(up.peers) <= up.peers.capacity and up.peers.evicted >= 300 - up.peers.capacity
        assert a.getsockname() in up.peers and up.peers.answer_address == a.getsockname()
        ground.send(mavlink.MAVLink_param_request_read_message(FSW_SYSID, FSW_COMPID, b"", 0), 1.0)
        up.params.register("X", lambda: 1.5, None, 0, 2)
        ground.send(mavlink.MAVLink_param_request_read_message(FSW_SYSID, FSW_COMPID, b"X", -1), 1.0)
        up.poll(1.0)
        values = [r.msg for r in ground.feed(b"".join(received(a)), 1.0)]
        assert [(v.get_type(), v.param_id, v.param_value) for v in values] == [("PARAM_VALUE", "X", 1.5)] * 2
        assert received(b) == [] and up.counters.foreign_datagrams >= 300
    finally:
        for s in (a, b):
            s.close()
        link.close()


def test_without_a_key_answers_go_to_the_last_well_formed_sender_only():
    link = UdpLink("udpin:127.0.0.1:0", source_system=FSW_SYSID, source_component=FSW_COMPID)
    box = link.sock.getsockname()
    up, runs = make_uplink(link, key=None)
    a, b = udp_socket(), udp_socket()
    try:
        b.sendto(b"\xfe" * 1000, box)  # noise: not well-formed, not answered
        GroundLink(lambda f: a.sendto(f, box), None).command_long(R.MAV_CMD_USER_1, [1], 0.0)
        up.poll(0.0)
        acks = GroundLink(lambda f: None, None).feed(b"".join(received(a)), 0.0)
        assert [(r.msg.command, r.msg.result) for r in acks] == [(R.MAV_CMD_USER_1, R.MAV_RESULT_DENIED)]
        assert received(b) == [] and runs == [] and up.peers.answer_address == a.getsockname()
    finally:
        for s in (a, b):
            s.close()
        link.close()


def test_telemetry_on_a_udpin_link_goes_to_the_ground_station_once_it_is_known():
    class Source:
        b_body_T = np.array([20e-6, -10e-6, 30e-6])
        sample_time_s = 0.0

        def update(self, now_s):
            self.sample_time_s = now_s
            self.b_body_T = self.b_body_T + 1e-8
            return True

    link = UdpLink("udpin:127.0.0.1:0", source_system=FSW_SYSID, source_component=FSW_COMPID)
    box = link.sock.getsockname()
    tlm = Telemetry(link, key=KEY, clock=SigningClock(epoch=T0, clock_set=True))
    fsw = FlightSoftware(Source(), tlm, rate_hz=10, sigma_b_T=1e-7, sample_rate_hz=10.0, uplink=link, key=KEY)
    a, b = udp_socket(), udp_socket()
    ground = GroundLink(lambda f: a.sendto(f, box), KEY, SigningClock(epoch=T0, clock_set=True))
    try:
        b.sendto(b"hello", box)
        for k in range(5):
            fsw.tick(k * 0.1)
        assert link.unaddressed_writes > 0 and received(a) == [] and received(b) == []
        ground.command_long(R.MAV_CMD_REQUEST_MESSAGE, [R.MAVLINK_MSG_ID_HEARTBEAT], 0.5)
        for k in range(5, 12):
            fsw.tick(k * 0.1)
        kinds = {r.msg.get_type() for r in ground.feed(b"".join(received(a)), 1.2) if r.verdict is Verdict.OK}
        assert {"COMMAND_ACK", "DEBRIS_MAG_SAMPLE", "HEARTBEAT"} <= kinds
        assert received(b) == []
    finally:
        for s in (a, b):
            s.close()
        link.close()


def test_peer_table_keeps_its_bound_and_the_answer_address():
    t = PeerTable(4)
    t.seen("ground", 50, 0.0)
    t.answer("ground", 0.0, authenticated=True)
    for i in range(100):
        t.seen(("spoof", i), 10, 1.0 + i)
    assert len(t) == 4 and "ground" in t and t.answer_address == "ground"
    assert t.evicted == 97 and t.sources == 101 and t.get(("spoof", 99)).datagrams == 1
    assert t.foreign(("spoof", 99)) and not t.foreign("ground")
    with pytest.raises(ValueError):
        PeerTable(1)


def test_forged_signed_frames_cost_no_decode(monkeypatch):
    """Frames with a good CRC and a wrong signature are refused on their raw bytes."""
    link = DatagramLink()
    up, runs = make_uplink(link)
    p = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    raw = mavlink.MAVLink_command_long_message(FSW_SYSID, FSW_COMPID, R.MAV_CMD_USER_1, 0, *[1.0] * 7).pack(p)
    for i in range(10):
        link.put(sign_frame(bytes(32), raw, 0, T0 + i))
    monkeypatch.setattr(up._deframer, "decode", lambda frame: pytest.fail("decoded a forged frame"))
    up.poll(0.0)
    assert up.counters.bad_signature == 10 and runs == []
