"""The frame parsers never fall over and never let a damaged or forged frame through: property-based
tests (hypothesis) of the deframer and the decoder, and a seeded fuzz run of random and mutated frames
through the flight software's uplink."""
import math

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fsw.commands import CommandRouter
from fsw.telemetry.dialect import FSW_COMPID, FSW_SYSID, mavlink
from fsw.telemetry.framing import Deframer
from fsw.telemetry.signing import SigningClock, unix_to_timestamp
from fsw.telemetry.uplink import Uplink
from ground.command import GroundLink
from ground.decode import Decoder
from ground.recording import read_recording, write_recording

KEY = bytes(range(7, 39))
T0 = unix_to_timestamp(1_750_000_000.0)
FAST = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def packer(sysid=FSW_SYSID, compid=FSW_COMPID):
    return mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)


def imu_frame(p, t_us, x):
    f = mavlink.MAVLink_highres_imu_message(t_us, 0, 0, 0, 0, 0, 0, x, 0.1, -0.2, 0, 0, 0, 0, 0x1C0).pack(p)
    p.seq = (p.seq + 1) % 256
    return f


def chunks(data: bytes, cuts: list[int]):
    edges = sorted({0, len(data), *(c % (len(data) + 1) for c in cuts)})
    return [data[a:b] for a, b in zip(edges, edges[1:])]


def run_deframer(data, cuts):
    d = Deframer()
    out = []
    for c in chunks(data, cuts):
        out += d.feed(c)
    return out + d.flush()


@FAST
@given(st.binary(max_size=2000), st.lists(st.integers(0, 4000), max_size=20))
def test_any_bytes_are_accounted_for_and_never_raise(data, cuts):
    out = run_deframer(data, cuts)
    # every byte is either in a frame or reported as rejected
    assert sum(len(m.get_msgbuf()) for m in out) == len(data)


no_stx = st.binary(max_size=60).map(lambda b: bytes(x for x in b if x not in (0xFD, 0xFE)))


@FAST
@given(st.lists(st.tuples(no_stx, st.floats(-8, 8, allow_nan=False)), min_size=1, max_size=30),
       st.lists(st.integers(0, 10_000), max_size=30))
def test_every_frame_in_line_noise_is_found_in_order(items, cuts):
    p = packer()
    stream = b""
    for k, (noise, x) in enumerate(items):
        stream += noise + imu_frame(p, k, x)
    out = [m for m in run_deframer(stream, cuts) if m.get_type() != "BAD_DATA"]
    assert [m.time_usec for m in out] == list(range(len(items)))


@FAST
@given(st.lists(st.integers(0, 10**6), min_size=1, max_size=20), st.data())
def test_a_damaged_frame_is_never_taken_for_a_good_one(times, data):
    """One byte changed anywhere in a frame (a burst of at most 8 bits: the CRC-16 catches it): that
    frame is refused, the others arrive."""
    p = packer()
    frames = [imu_frame(p, t, 0.25) for t in times]
    k = data.draw(st.integers(0, len(frames) - 1))
    i = data.draw(st.integers(0, len(frames[k]) - 1))
    v = data.draw(st.integers(1, 255))
    bad = bytearray(frames[k])
    bad[i] ^= v
    frames[k] = bytes(bad)
    out = [m for m in run_deframer(b"".join(frames), []) if m.get_type() != "BAD_DATA"]
    assert [m.time_usec for m in out] == [t for j, t in enumerate(times) if j != k]


finite = st.floats(-1e3, 1e3, allow_nan=False)


@FAST
@given(samples=st.lists(st.tuples(st.integers(0, 10**9), finite, st.one_of(finite, st.just(math.nan))),
                        max_size=60))
def test_decoder_keeps_a_valid_recording_whatever_the_order(samples, tmp_path_factory):
    """Samples in any order, repeated, with non-finite values: the recording is sorted, unique, finite,
    and writes and reads back."""
    p = packer()
    dec = Decoder()
    for m in run_deframer(b"".join(imu_frame(p, t, x) if math.isfinite(y) else
                                   mavlink.MAVLink_highres_imu_message(t, 0, 0, 0, 0, 0, 0, y, 0, 0, 0, 0, 0, 0,
                                                                       0x1C0).pack(p)
                                   for t, x, y in samples), []):
        dec.handle(m, 0.0)
    rec = dec.recording()
    assert np.all(np.diff(rec.t_s) > 0) and np.isfinite(rec.b_T).all()
    if len(rec):
        path = tmp_path_factory.mktemp("rec") / "r.csv"
        write_recording(path, rec)
        back = read_recording(path)
        np.testing.assert_array_equal(back.t_s, rec.t_s)


def make_uplink(key=KEY):
    router = CommandRouter()
    runs = []
    router.register(mavlink.MAV_CMD_USER_1, lambda m, t: runs.append(m.param1))
    replies = []
    up = Uplink(None, router, sysid=FSW_SYSID, compid=FSW_COMPID, key=key,
                clock=SigningClock(epoch=T0, clock_set=True), reply=replies.append)
    return up, runs, replies


def test_fuzz_the_uplink_with_random_and_mutated_frames():
    """A seeded fuzz run: 3000 inputs — random bytes, signed command frames with bytes flipped, cut,
    spliced or repeated — never raise, and only the untouched genuine frames are obeyed."""
    rng = np.random.default_rng(2024)
    up, runs, _ = make_uplink()
    ground = GroundLink(lambda b: None, KEY, SigningClock(epoch=T0))
    genuine = 0
    for k in range(3000):
        frame = bytearray(ground.command_long(mavlink.MAV_CMD_USER_1, [k], 0.0))
        kind = k % 6
        if kind == 0:
            data = rng.integers(0, 256, int(rng.integers(1, 300))).astype(np.uint8).tobytes()
        elif kind == 1:
            for _ in range(int(rng.integers(1, 4))):
                frame[int(rng.integers(len(frame)))] ^= int(rng.integers(1, 256))
            data = bytes(frame)
        elif kind == 2:
            data = bytes(frame[: int(rng.integers(1, len(frame)))])
        elif kind == 3:
            junk = rng.integers(0, 256, int(rng.integers(0, 40))).astype(np.uint8).tobytes()
            data = junk + bytes(frame) + junk
            genuine += 1
        elif kind == 4:
            data = bytes(frame) + bytes(frame)           # the second copy is a replay
            genuine += 1
        else:
            data = bytes([0xFD, int(rng.integers(256)), 1]) + rng.integers(0, 256, 290).astype(np.uint8).tobytes()
        up.feed(data, k * 0.01)
    assert len(runs) == genuine
    assert up.counters.replay >= 500 and up.counters.parser_resets == 0


@FAST
@given(st.binary(max_size=600), st.lists(st.integers(0, 1000), max_size=8))
def test_uplink_never_raises_and_never_obeys_noise(data, cuts):
    for key in (KEY, None):
        up, runs, _ = make_uplink(key)
        for c in chunks(data, cuts):
            up.feed(c, 0.0)
        assert runs == []


def test_a_command_after_a_frame_cut_in_its_signature_is_obeyed_whatever_the_reads():
    """Found by the fuzz (tests/test_fuzz_readers.py): a signed frame that lost the last bytes of its
    signature, then a command read in two pieces. The cut frame took the command's first bytes as its
    signature (the CRC does not cover it) and the command was lost, unless it had arrived whole."""
    ground = GroundLink(lambda b: None, KEY, SigningClock(epoch=T0))
    for lost in (1, 3, 12):
        cut = ground.command_long(mavlink.MAV_CMD_USER_1, [1], 0.0)[:-lost]
        good = ground.command_long(mavlink.MAV_CMD_USER_1, [2], 0.01)
        data = cut + good
        for split in range(len(cut) - 5, len(data) + 1):
            up, runs, _ = make_uplink()
            up.feed(data[:split], 0.0)
            up.feed(data[split:], 0.01)
            assert runs == [2], (lost, split)
            assert up.counters.bad_signature + up.counters.garbage_bytes > 0   # the cut frame: refused


def test_a_command_whose_signature_ends_in_a_start_byte_is_obeyed_at_once():
    """A signed frame with a start byte in its signature block is passed on as soon as it is whole,
    not held until more bytes arrive (the last thing the ground sends is a command)."""
    ground = GroundLink(lambda b: None, KEY, SigningClock(epoch=T0))
    for k in range(2000):
        frame = ground.command_long(mavlink.MAV_CMD_USER_1, [k], 0.0)
        if frame[-1] == 0xFD:
            break
    else:
        raise AssertionError("no signature ending in 0xFD in 2000 frames")
    up, runs, _ = make_uplink()
    up.feed(frame, 0.0)
    assert runs == [k]


def test_a_chance_crc_match_in_noise_does_not_swallow_the_frame_it_runs_into():
    """Found by the fuzz (tests/test_fuzz_readers.py): a valid-looking COMMAND_LONG header in noise
    declares 45 bytes that end inside the sample after it, and those bytes pass its CRC-16 by chance
    (here forced by two chosen noise bytes). Of the two overlapping frames the one whose end meets the
    end of the data or the next frame is taken: the sample, not the noise."""
    from fsw.telemetry.framing import MESSAGES, crc_x25
    p = packer()
    sample = imu_frame(p, 439060853, 0.5)
    header = bytes([0xFD, 33, 0, 0, 0, 255, 190, mavlink.MAVLINK_MSG_ID_COMMAND_LONG, 0, 0])
    extra = MESSAGES[mavlink.MAVLINK_MSG_ID_COMMAND_LONG][0]
    want = sample[29] | sample[30] << 8  # the noise frame's CRC bytes: the sample's bytes 29 and 30
    noise = next(header + bytes([7, 9, x, y]) for x in range(256) for y in range(256)
                 if crc_x25(header[1:] + bytes([7, 9, x, y]) + sample[:29], extra) == want)
    for tail, times in ((b"", [439060853]), (imu_frame(p, 439060854, 0.25), [439060853, 439060854])):
        out = [m for m in run_deframer(noise + sample + tail, []) if m.get_type() != "BAD_DATA"]
        assert [getattr(m, "time_usec", m.get_type()) for m in out] == times
