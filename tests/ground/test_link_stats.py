"""Loss accounting from hand-built MAVLink 2 frame sequences (packed with the project dialect, seq set
explicitly, decoded by pymavlink's robust parser exactly as on the link)."""
from __future__ import annotations

import struct

import numpy as np
import pytest

from fsw.telemetry.dialect import FSW_COMPID, FSW_SYSID, mavlink
from ground.link_stats import REORDER_WINDOW, LinkStats, frames_lost, samples_missing

FSW = (FSW_SYSID, FSW_COMPID)


def pack(msg, seq: int, src: tuple[int, int] = FSW) -> bytes:
    packer = mavlink.MAVLink(None, srcSystem=src[0], srcComponent=src[1])
    packer.seq = seq % 256
    return bytes(msg.pack(packer))


def heartbeat(custom_mode: int = 0):
    return mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
                                             mavlink.MAV_AUTOPILOT_INVALID, 0, custom_mode, 0, 3)


def imu(time_usec: int):
    return mavlink.MAVLink_highres_imu_message(time_usec, 0, 0, 0, 0, 0, 0, 0.2, -0.1, 0.4, 0, 0, 0, 0,
                                               0x1C0)


def feed(stats: LinkStats, stream: bytes, now_s: float = 0.0) -> list:
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    msgs = parser.parse_buffer(stream) or []
    for m in msgs:
        stats.on_frame(m, now_s)
    return msgs


def src_summary(stats: LinkStats, src=FSW) -> dict:
    return stats.summary()["sources"][src]


def test_frames_lost_wraps_at_256() -> None:
    assert frames_lost(5, 5) == 0
    assert frames_lost(7, 5) == 2
    assert frames_lost(3, 250) == 9
    assert frames_lost(4, 5) == 255  # what a naive counter books for a repeated frame


def test_in_order_stream_across_wraps_loses_nothing() -> None:
    stats = LinkStats()
    feed(stats, b"".join(pack(heartbeat(k), k) for k in range(600)))
    s = src_summary(stats)
    assert (s["received"], s["lost"], s["duplicates"], s["out_of_sequence"]) == (600, 0, 0, 0)


def test_skipped_sequence_numbers_count_as_lost() -> None:
    stats = LinkStats()
    sent = [k for k in range(40) if k not in (5, 20, 21, 22)]
    feed(stats, b"".join(pack(heartbeat(k), k) for k in sent))
    s = src_summary(stats)
    assert s["received"] == 36 and s["lost"] == 4
    assert s["loss_fraction"] == pytest.approx(4 / 40)


def test_gap_across_the_wrap() -> None:
    stats = LinkStats()
    feed(stats, b"".join(pack(heartbeat(k), k) for k in [250, 251, 252, 253, 254, 255, 256 + 3, 256 + 4]))
    assert src_summary(stats)["lost"] == 3  # 0, 1, 2


def test_duplicate_frame_is_a_duplicate_not_255_lost() -> None:
    stats = LinkStats()
    frames = [pack(heartbeat(k), k) for k in range(10)]
    feed(stats, b"".join(frames[:5] + [frames[4]] + frames[5:] + [frames[9], frames[9]]))
    s = src_summary(stats)
    assert (s["received"], s["lost"], s["duplicates"]) == (10, 0, 3)


def test_repeated_seq_with_other_payload_is_not_255_lost() -> None:
    stats = LinkStats()
    feed(stats, b"".join([pack(heartbeat(0), 0), pack(heartbeat(1), 1), pack(heartbeat(99), 1),
                          pack(heartbeat(2), 2)]))
    s = src_summary(stats)
    assert (s["received"], s["lost"], s["duplicates"], s["out_of_sequence"]) == (4, 0, 0, 1)


def test_late_frame_takes_its_loss_back() -> None:
    stats = LinkStats()
    order = [0, 1, 2, 4, 5, 3, 6, 10, 8, 7, 9, 11]
    frames = {k: pack(heartbeat(k), k) for k in order}
    feed(stats, b"".join(frames[k] for k in order[:5]))
    assert src_summary(stats)["lost"] == 1
    feed(stats, b"".join(frames[k] for k in order[5:]))
    s = src_summary(stats)
    assert (s["received"], s["lost"], s["late"], s["out_of_sequence"]) == (12, 0, 4, 0)
    feed(stats, frames[3])  # the late frame again: a duplicate
    assert src_summary(stats)["duplicates"] == 1


def test_old_missing_frame_beyond_the_window_stays_lost() -> None:
    stats = LinkStats()
    seqs = [0] + list(range(2, 2 + 2 * REORDER_WINDOW))
    feed(stats, b"".join(pack(heartbeat(k), k) for k in seqs))
    feed(stats, pack(heartbeat(1), 1))  # seq 1, 32 frames late: beyond the window
    s = src_summary(stats)
    # the documented limit of an 8-bit counter: read as a gap of (1 - 34) mod 256 = 223 frames
    assert (s["late"], s["lost"]) == (0, 1 + 223)


def test_sources_are_independent() -> None:
    stats = LinkStats()
    other = (2, mavlink.MAV_COMP_ID_AUTOPILOT1)
    stream = []
    for k in range(20):
        if k != 7:
            stream.append(pack(heartbeat(k), k, FSW))
        if k % 2 == 0:
            stream.append(pack(heartbeat(k), 100 + k // 2, other))
    feed(stats, b"".join(stream))
    summary = stats.summary()
    assert summary["sources"][FSW]["lost"] == 1 and summary["sources"][FSW]["received"] == 19
    assert summary["sources"][other]["lost"] == 0 and summary["sources"][other]["received"] == 10
    assert summary["totals"]["received"] == 29 and summary["totals"]["lost"] == 1


def test_garbage_bytes_are_counted_exactly_and_frames_around_them_survive() -> None:
    stats = LinkStats()
    rng = np.random.default_rng(7)
    garbage = bytes(b for b in rng.integers(0, 256, 200).tolist() if b not in (0xFD, 0xFE))
    msgs = feed(stats, pack(heartbeat(0), 0) + garbage + pack(heartbeat(1), 1) + b"\x00\x01\x02"
                + pack(heartbeat(2), 2))
    summary = stats.summary()
    assert summary["garbage_bytes"] == len(garbage) + 3 and summary["garbage_chunks"] == 2
    assert summary["sources"][FSW]["received"] == 3 and summary["sources"][FSW]["lost"] == 0
    assert [m.get_type() for m in msgs].count("HEARTBEAT") == 3


def test_bad_crc_frame_is_rejected_counted_and_its_seq_is_lost() -> None:
    stats = LinkStats()
    bad = bytearray(pack(heartbeat(1), 1))
    bad[12] ^= 0x40  # one payload bit flipped in transit
    msgs = feed(stats, pack(heartbeat(0), 0) + bytes(bad) + pack(heartbeat(2), 2))
    assert [m.get_type() for m in msgs] == ["HEARTBEAT", "BAD_DATA", "HEARTBEAT"]
    summary = stats.summary()
    assert summary["bad_crc"] == 1 and summary["garbage_bytes"] == 0
    assert summary["sources"][FSW]["lost"] == 1 and summary["sources"][FSW]["received"] == 2


def _unknown_frame(seq: int, msgid: int = 54099, src=FSW) -> bytes:
    payload = bytes(range(1, 9))
    header = struct.pack("<BBBBBBBHB", 0xFD, len(payload), 0, 0, seq, src[0], src[1], msgid & 0xFFFF,
                         msgid >> 16)
    return header + payload + b"\x12\x34"  # CRC unknown without the message's CRC_EXTRA


def test_unknown_message_is_counted_and_keeps_the_sequence() -> None:
    stats = LinkStats()
    msgs = feed(stats, pack(heartbeat(0), 0) + _unknown_frame(1) + pack(heartbeat(2), 2))
    assert [m.get_type() for m in msgs] == ["HEARTBEAT", "UNKNOWN_54099", "HEARTBEAT"]
    summary = stats.summary()
    assert summary["unknown"] == 1
    s = summary["sources"][FSW]
    assert (s["received"], s["unknown"], s["lost"]) == (2, 1, 0)


def test_unknown_message_from_a_new_source_does_not_create_it() -> None:
    stats = LinkStats()
    feed(stats, _unknown_frame(9, src=(42, 42)))
    assert stats.summary()["unknown"] == 1 and stats.summary()["sources"] == {}


def test_unsupported_incompat_flags_are_malformed() -> None:
    stats = LinkStats()
    frame = bytearray(pack(heartbeat(0), 0))
    frame[2] = 0x02  # an incompatibility flag this parser does not know
    feed(stats, bytes(frame) + pack(heartbeat(1), 1))
    summary = stats.summary()
    assert summary["malformed"] == 1 and summary["sources"][FSW]["received"] == 1


def test_samples_missing_sees_an_outage_longer_than_256_frames() -> None:
    """300 consecutive samples lost (10 Hz): seq alone reports 300 mod 256 = 44, the sample clock 300."""
    stats = LinkStats()
    kept = [k for k in range(1000) if not 400 <= k < 700]
    feed(stats, b"".join(pack(imu(100_000 * k), k) for k in kept))
    s = src_summary(stats)
    assert s["lost"] == 300 % 256
    assert s["samples"] == 700 and s["samples_missing"] == 300


def test_samples_missing_isolated_gaps_with_jitter() -> None:
    rng = np.random.default_rng(3)
    t = np.arange(500) * 50_000 + rng.integers(-2_000, 2_000, 500)  # 20 Hz, ±2 ms jitter
    keep = np.ones(500, bool)
    keep[[10, 11, 200, 420, 421, 422]] = False
    assert samples_missing(t[keep]) == 6
    assert samples_missing(t) == 0
    assert samples_missing(t[keep][::-1]) == 6  # order does not matter
    assert samples_missing(np.concatenate([t, t[:50]])) == 0  # repeated samples are not gaps


def test_duplicated_sample_frames_are_not_samples_twice() -> None:
    stats = LinkStats()
    frames = [pack(imu(100_000 * k), k) for k in range(20)]
    feed(stats, b"".join(frames + frames[-3:]))
    s = src_summary(stats)
    assert (s["samples"], s["samples_missing"], s["duplicates"]) == (20, 0, 3)


def test_only_magnetometer_samples_are_timed() -> None:
    stats = LinkStats()
    no_mag = mavlink.MAVLink_highres_imu_message(5, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0x7)
    feed(stats, pack(no_mag, 0))
    assert src_summary(stats)["samples"] == 0


def test_first_and_last_seen_times() -> None:
    stats = LinkStats()
    feed(stats, pack(heartbeat(0), 0), now_s=10.0)
    feed(stats, pack(heartbeat(1), 1), now_s=12.5)
    s = src_summary(stats)
    assert (s["first_s"], s["last_s"]) == (10.0, 12.5)


def _state(src) -> tuple:
    return (src.as_dict(), src.expected, list(src.recent), list(src.missing))


@pytest.mark.parametrize("seed", range(6))
def test_a_run_accounted_at_once_is_what_frame_by_frame_accounting_gives_or_is_refused(seed):
    """`LinkStats.on_run` (the archive export's bulk accounting) against `on_frame` one by one: a run it
    takes leaves the same counters; it refuses, changing nothing, every run with a loss, a copy, a late or
    an out-of-sequence frame, which then go one by one."""
    rng = np.random.default_rng(seed)
    parser = mavlink.MAVLink(None)
    seq, sent = 0, []
    for k in range(3000):
        sent.append(pack(heartbeat(k), seq))
        seq += 1
        event = rng.random()
        if event < 0.002:
            seq += int(rng.integers(1, 300))                         # lost frames
        elif event < 0.004:
            sent.append(sent[-1])                                    # a copy
        elif event < 0.006 and len(sent) > 3:
            sent.append(sent[-3])                                    # a late copy
        elif event < 0.008:
            sent[-1], sent[-2] = sent[-2], sent[-1]                  # reordered
    bulk, one = LinkStats(), LinkStats()
    taken = refused = 0
    i = 0
    while i < len(sent):
        run = sent[i:i + int(rng.integers(1, 80))]
        i += len(run)
        before = {k: _state(s) for k, s in bulk.sources.items()}
        seqs = np.array([f[4] for f in run])
        ok = bulk.on_run(FSW, seqs, run, float(i), float(i + 1))
        verdicts, lost = [], one.lost()
        for f in run:
            one.on_frame(parser.decode(bytearray(f)), float(i + 1))
            verdicts.append(one.last_verdict)
        clean = set(verdicts) == {"new"} and one.lost() == lost
        assert ok == clean
        if ok:
            taken += 1
        else:
            refused += 1
            assert {k: _state(s) for k, s in bulk.sources.items()} == before
            for f in run:                                            # then frame by frame
                bulk.on_frame(parser.decode(bytearray(f)), float(i + 1))
        src, ref = bulk.sources[FSW], one.sources[FSW]
        assert _state(src)[1:] == _state(ref)[1:]
        assert {k: v for k, v in src.as_dict().items() if k != "first_s"} == \
               {k: v for k, v in ref.as_dict().items() if k != "first_s"}
    assert taken > 20 and refused > 10
