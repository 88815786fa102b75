"""The export's bulk decoding of the sample messages (`ground.archive.bulk`) against pymavlink's one-by-one
decoding and `ground.decode.f32`, and the recordings' row formatting against the one-value-at-a-time one."""
from __future__ import annotations

import math

import numpy as np
import pytest

from fsw.telemetry.dialect import mavlink
from ground.archive.bulk import LAYOUTS, decode_samples
from ground.decode import F32_FIELDS, f32
from ground.recording import _format, _format_exact, _lines

SPECIAL = [0.0, -0.0, 0.1, -0.3, 1e-45, 1.17549435e-38, 3.4028235e38, -3.4028235e38, math.inf, -math.inf,
           math.nan, 123456.789, 16777217.0, 1e-7]


def _values(rng, n):
    """float32-representable values of every magnitude, and the special ones."""
    x = rng.normal(0, 1, n) * 10.0 ** rng.integers(-40, 38, n)
    x[: len(SPECIAL)] = SPECIAL
    return np.float32(x).astype(float).tolist()


def _messages(rng):
    v = iter(_values(rng, 6000))
    out = []
    for k in range(120):
        t = int(rng.integers(0, 2**63))
        kit = [next(v) for _ in range(3)] if k % 3 else [0.0, 0.0, 0.0]      # zeros: a truncated payload
        out.append(mavlink.MAVLink_debris_mag_sample_message(t, k, 0x1234 + k, [next(v) for _ in range(3)],
                                                             k % 4, kit))
        out.append(mavlink.MAVLink_debris_rate_estimate_message(t, *(next(v) for _ in range(6)), k % 3, k % 2))
        out.append(mavlink.MAVLink_debris_sim_state_message(t, next(v), next(v), next(v),
                                                            [next(v) for _ in range(4)],
                                                            *(next(v) for _ in range(6))))
        out.append(mavlink.MAVLink_highres_imu_message(t, *(next(v) for _ in range(13)), 0x1C0 + k, k % 2))
    return out


def _pack(msgs, signed=False, v1=False):
    mav = mavlink.MAVLink(None, srcSystem=7, srcComponent=191)
    if signed:
        mav.signing.secret_key = bytes(range(32))
        mav.signing.sign_outgoing = True
        mav.signing.timestamp = 1
    frames = []
    for m in msgs:
        frames.append(bytes(m.pack(mav, force_mavlink1=v1)))
        mav.seq = (mav.seq + 1) % 256
    return frames


def _same(a, b):
    return a == b or (isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b)
                      and math.copysign(1, a) == math.copysign(1, b))


@pytest.mark.parametrize("signed, v1", [(False, False), (True, False), (False, True)])
def test_bulk_decoding_is_pymavlinks_with_the_decoders_rounding(signed, v1):
    msgs = _messages(np.random.default_rng(3))
    if v1:   # ids above 255 are MAVLink 2 only
        msgs = [m for m in msgs if m.get_type() == "HIGHRES_IMU"]
    frames = _pack(msgs, signed, v1)
    parser = mavlink.MAVLink(None)
    checked = 0
    for msgid in LAYOUTS:
        mine = [f for f in frames if (f[7] | f[8] << 8 | f[9] << 16 if f[0] == 0xFD else f[5]) == msgid]
        if not mine:
            continue
        for frame, got in zip(mine, decode_samples(mine, msgid)):
            ref = parser.decode(bytearray(frame))
            assert got is not None
            assert (got.get_type(), got.get_msgId(), got.get_seq(), got.get_srcSystem(), got.get_srcComponent(),
                    bytes(got.get_msgbuf())) == (ref.get_type(), ref.get_msgId(), ref.get_seq(), ref.get_srcSystem(),
                                                 ref.get_srcComponent(), frame)
            for name in ref.get_fieldnames():
                want = getattr(ref, name)
                if name in F32_FIELDS[ref.get_type()]:
                    want = f32(*want) if isinstance(want, list) else f32(want)[0]
                have = getattr(got, name)
                if isinstance(want, (list, tuple)):
                    assert len(have) == len(want) and all(map(_same, have, want)), name
                else:
                    assert _same(have, want), name
                checked += 1
    assert checked >= 1920


def test_a_frame_pymavlink_would_refuse_is_left_to_it():
    msgs = [mavlink.MAVLink_debris_rate_estimate_message(k, 0.1, 0.2, 0.3, 0.01, 0.01, 0.01, 1, 0) for k in range(3)]
    good, bad_crc, short = _pack(msgs)
    bad_crc = bad_crc[:-1] + bytes([bad_crc[-1] ^ 1])
    short = short[:-3]
    msgid = mavlink.MAVLINK_MSG_ID_DEBRIS_RATE_ESTIMATE
    got = decode_samples([good, bad_crc, short], msgid)
    assert got[0] is not None and got[0].wx == 0.1 and got[1:] == [None, None]


def test_rows_are_formatted_as_one_value_at_a_time():
    rng = np.random.default_rng(5)
    table = rng.normal(0, 1, (3000, 7)) * 10.0 ** rng.integers(-320, 308, (3000, 7))
    table[:2, 1:] = [[math.nan, -math.nan, math.inf, -math.inf, -0.0, 5e-324],
                     [1.7976931348623157e308, -1.7976931348623157e308, 1.79769313486231e308, 0.1, 1e-7, 2.5]]
    want = [",".join([_format_exact(r[0]), *map(_format, r[1:])]) for r in table.tolist()]
    assert _lines(table) == want
