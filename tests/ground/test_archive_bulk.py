"""The export's bulk decoding of the sample messages (`ground.archive.bulk`) against pymavlink's one-by-one
decoding and `ground.decode.f32`, and the recordings' row formatting against the one-value-at-a-time one."""
from __future__ import annotations

import math

import numpy as np
import pytest

from fsw.telemetry.dialect import mavlink
from ground.archive.bulk import LAYOUTS, _f32_decimals, _f32_decimals_by_text, decode_samples
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


def test_a_batch_of_raw_frames_decodes_to_pymavlinks_messages():
    """`decode_frames` (the ground station's ingest): the sample messages decoded in bulk, not rounded, every
    other message by pymavlink, junk passed through, in the batch's order: each the value pymavlink gives."""
    from fsw.telemetry.framing import Deframer
    from ground.archive.bulk import decode_frames

    msgs = _messages(np.random.default_rng(8))[:40]
    msgs.insert(5, mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GENERIC, mavlink.MAV_AUTOPILOT_INVALID,
                                                     0, 0, mavlink.MAV_STATE_ACTIVE, 3))
    msgs.insert(9, mavlink.MAVLink_statustext_message(mavlink.MAV_SEVERITY_INFO, b"hello"))
    deframer = Deframer()
    items = []
    for i, frame in enumerate(_pack(msgs, signed=True)):
        items += deframer.feed_frames(frame, end=True)
        if i == 20:
            items += deframer.feed_frames(b"\x01\x02junk", end=True)
    assert sum(isinstance(x, bytes) for x in items) == len(msgs) and len(items) == len(msgs) + 1
    got = decode_frames(items, Deframer().decode)
    ref = Deframer()
    for item, have in zip(items, got):
        if not isinstance(item, bytes):
            assert have is item and have.get_type() == "BAD_DATA"
            continue
        want = ref.decode(item)
        assert (have.get_type(), have.get_msgId(), have.get_seq(), have.get_srcSystem(),
                have.get_srcComponent(), bytes(have.get_msgbuf())) == \
               (want.get_type(), want.get_msgId(), want.get_seq(), want.get_srcSystem(),
                want.get_srcComponent(), item)
        for name in want.get_fieldnames():
            a, b = getattr(have, name), getattr(want, name)
            if isinstance(b, (list, tuple)):
                assert len(a) == len(b) and all(map(_same, a, b)), name
            else:
                assert _same(a, b), name


def test_a_batch_archived_at_once_holds_what_frame_by_frame_does(tmp_path):
    from fsw.telemetry.framing import Deframer
    from ground.archive import ArchiveWriter, open_reader

    msgs = [Deframer().decode(f) for f in _pack(_messages(np.random.default_rng(9))[:60])]
    times = [1_750_000_000 + 0.01 * k for k in range(len(msgs))]
    with ArchiveWriter(tmp_path / "one.sqlite") as w:
        for m, t in zip(msgs, times):
            w.add(m, t)
    with ArchiveWriter(tmp_path / "many.sqlite") as w:
        w.add_many(msgs[:25], times[:25])
        w.add_many(msgs[25:], times[25:])
    rows = [open_reader(tmp_path / n).execute("SELECT t_us, sysid, compid, msgid, box_t_us, frame FROM frames "
                                              "ORDER BY rowid").fetchall() for n in ("one.sqlite", "many.sqlite")]
    assert len(rows[0]) == 60 and rows[0] == rows[1]


def test_float32_decimals_without_text_are_the_decoders():
    """The export's rounding of float32 values to their shortest decimal (`_f32_decimals`, arithmetic) is
    `ground.decode.f32`'s (NumPy's text of the float32 read back) on every value: a million random bit
    patterns (every exponent, NaN, ±inf, subnormals), field-like values, exact ties between two decimals
    (21.1796875: round half to even) and powers of ten at the edges of the arithmetic's range."""
    rng = np.random.default_rng(11)
    bits = rng.integers(0, 2 ** 32, 1_000_000, dtype=np.uint64).astype(np.uint32).view(np.float32)
    special = np.array([0.0, -0.0, math.nan, math.inf, -math.inf, 1e-45, -3.4e38, 21.1796875, -42.8671875,
                        1956818.75, 0.1, 0.3, 1.0, 9.999999, 10.0, 1e-12, 9.99e-13, 1e13, 9.999e12, 16777217.0],
                       dtype=np.float32)
    for v in (bits, special, rng.normal(0.0, 0.5, 200_000).astype(np.float32),      # gauss: the field
              (10.0 ** rng.uniform(-13.0, 14.0, 300_000)).astype(np.float32),
              rng.uniform(-1e6, 1e6, 200_000).astype(np.float32)):
        with np.errstate(invalid="ignore"):
            got, want = _f32_decimals(v), _f32_decimals_by_text(v)
        same = (got == want) & (np.signbit(got) == np.signbit(want)) | (np.isnan(got) & np.isnan(want))
        assert same.all(), (v[~same][:5], got[~same][:5], want[~same][:5])
    # the decoder's own f32, value by value: −0.0 beside +0.0 keeps its sign (it once took +0.0's or gave its own)
    by_decoder = np.array([f32(float(x))[0] for x in special])
    for got in (_f32_decimals(special), _f32_decimals_by_text(special)):
        np.testing.assert_array_equal(got, by_decoder)
        assert (np.signbit(got) == np.signbit(by_decoder)).all()
    assert _f32_decimals(np.float32([[30.0, 0.299995]])).tolist() == [[30.0, 0.299995]]
    assert _f32_decimals(np.float32([29.976004])).tolist() == [f32(29.976004)[0]]
