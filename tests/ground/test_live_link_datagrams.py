"""The station's UDP link takes a datagram that is exactly one intact frame as it is
(`fsw.telemetry.framing.intact_frame`), without the deframer's search: only when the deframer would find that
frame and nothing else in it."""
from __future__ import annotations

import numpy as np

from fsw.telemetry.dialect import mavlink
from fsw.telemetry.framing import Deframer, intact_frame


def _frames(rng) -> list[bytes]:
    mav = mavlink.MAVLink(None, srcSystem=3, srcComponent=191)
    signed = mavlink.MAVLink(None, srcSystem=3, srcComponent=191)
    signed.signing.secret_key = bytes(range(32))
    signed.signing.sign_outgoing = True
    signed.signing.timestamp = 1
    out = []
    for k in range(60):
        msg = (mavlink.MAVLink_debris_rate_estimate_message(k, *rng.normal(size=6), 2, 0) if k % 3 else
               mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GENERIC, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 4, 3))
        out.append(bytes(msg.pack(signed if k % 2 else mav, force_mavlink1=(k % 7 == 0 and k % 3 == 0))))
    return out


def test_a_datagram_is_taken_whole_only_when_the_deframer_finds_exactly_that_frame():
    rng = np.random.default_rng(4)
    frames = _frames(rng)
    datagrams = [b"", b"\xfd", bytes(rng.integers(0, 256, 40, dtype=np.uint8))]
    for f in frames:
        datagrams += [f, f[:-1], f + b"\x00", f + f, f[:5] + bytes([f[5] ^ 1]) + f[6:],
                      f[:-3] + bytes([f[-3] ^ 0x10]) + f[-2:], bytes([f[0], f[1] + 1]) + f[2:]]
    for mavlink1 in (False, True):
        for d in datagrams:
            if intact_frame(d, mavlink1):
                assert Deframer(mavlink1=mavlink1).feed_frames(d, end=True) == [d]
        # and the frames themselves, each alone in its datagram, are taken (MAVLink 1 only when asked for)
        assert [intact_frame(f, mavlink1) for f in frames] == [mavlink1 or f[0] == 0xFD for f in frames]
    assert any(f[0] == 0xFE for f in frames) and any(f[2] & 1 for f in frames if f[0] == 0xFD)
