"""MAVLink 2 signing: the verifier against pymavlink's own signer, every rejection reason, the lock-out
attack that works on pymavlink's check and not on ours, key files."""
import hashlib
import os
import stat

import pytest

from fsw.telemetry.dialect import mavlink
from fsw.telemetry.signing import (KEY_FILE_MAX_BYTES, NEW_STREAM_WINDOW, TICKS_PER_S, TIMESTAMP_MAX, KeyFileError,
                                   SigningClock, Verdict, Verifier, is_signed, load_key, setup_outgoing, sign_frame,
                                   signature_fields, unix_to_timestamp, write_key)
from ground import keys

KEY = bytes(range(32))
T0 = unix_to_timestamp(1_750_000_000.0)


def packer(key=KEY, ts=T0, sysid=255, compid=190, link_id=0):
    """pymavlink's own signer (sign_packet), set up as the ground would."""
    p = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    if key is not None:
        p.signing.secret_key = key
        p.signing.sign_outgoing = True
        p.signing.link_id = link_id
        p.signing.timestamp = ts
    return p


def command(p, cmd=mavlink.MAV_CMD_USER_1):
    frame = mavlink.MAVLink_command_long_message(1, 191, cmd, 0, 1, 2, 3, 4, 5, 6, 7).pack(p)
    p.seq = (p.seq + 1) % 256
    return frame


def verifier(**kw):
    return Verifier(KEY, SigningClock(epoch=T0, clock_set=True), **kw)


def test_accepts_frames_signed_by_pymavlink_and_pins_the_formula():
    frame = command(packer())
    assert is_signed(frame)
    sysid, compid, link_id, ts = signature_fields(frame)
    assert (sysid, compid, link_id, ts) == (255, 190, 0, T0)
    # MAVLink 2 signing: first 48 bits of SHA-256(secret key + frame up to the timestamp)
    assert frame[-6:] == hashlib.sha256(KEY + frame[:-6]).digest()[:6]
    assert verifier().check(frame, 0.0) is Verdict.OK


def test_rejection_reasons():
    v = verifier()
    assert v.check(command(packer(key=None)), 0.0) is Verdict.UNSIGNED
    assert v.check(command(packer(key=bytes(32))), 0.0) is Verdict.BAD_SIGNATURE
    p = packer()
    first = command(p)
    assert v.check(first, 0.0) is Verdict.OK
    assert v.check(first, 0.0) is Verdict.REPLAY                 # the same frame again
    assert v.check(command(p), 0.0) is Verdict.OK                # the next one (timestamp + 1)
    older = command(packer(ts=T0 - 5))                            # same stream, older timestamp
    assert v.check(older, 0.0) is Verdict.REPLAY
    # a new stream more than a minute behind our clock: a recording played back later
    stale = command(packer(ts=T0 - NEW_STREAM_WINDOW - 1, sysid=254))
    assert v.check(stale, 0.0) is Verdict.REPLAY
    recent = command(packer(ts=T0 - NEW_STREAM_WINDOW + TICKS_PER_S, sysid=253))
    assert v.check(recent, 0.0) is Verdict.OK
    assert v.counts[Verdict.REPLAY] == 3 and v.counts[Verdict.OK] == 3


def test_a_damaged_signature_or_payload_is_refused():
    frame = bytearray(command(packer()))
    frame[-1] ^= 0x01
    assert verifier().check(bytes(frame), 0.0) is Verdict.BAD_SIGNATURE


def lockout_frame():
    """A frame on the ground's stream (255/190, link 0) with the largest timestamp and a signature made
    with some other key: what a stranger without the key can send."""
    raw = command(packer(key=None))
    return sign_frame(os.urandom(32), raw, 0, TIMESTAMP_MAX)


def test_lockout_attack_locks_out_pymavlinks_check():
    """pymavlink 2.4.x stores the stream timestamp before comparing the signature: after one forged
    frame the genuine ground station is refused. (Documents why the project verifies itself.)"""
    rx = mavlink.MAVLink(None)
    rx.signing.secret_key = KEY
    rx.robust_parsing = True
    genuine = packer()
    assert rx.parse_buffer(command(genuine))[0].get_type() == "COMMAND_LONG"
    forged = rx.parse_buffer(lockout_frame())[0]
    assert forged.get_type() == "BAD_DATA"
    after = rx.parse_buffer(command(genuine))[0]
    assert after.get_type() == "BAD_DATA"           # the genuine ground station is now locked out
    assert rx.signing.stream_timestamps[(0, 255, 190)] == TIMESTAMP_MAX


def test_lockout_attack_does_not_work_against_the_verifier():
    v = verifier()
    genuine = packer()
    assert v.check(command(genuine), 0.0) is Verdict.OK
    before = dict(v.streams)
    for _ in range(3):
        assert v.check(lockout_frame(), 0.0) is Verdict.BAD_SIGNATURE
    assert {k: list(d) for k, d in v.streams.items()} == {k: list(d) for k, d in before.items()}
    assert v.clock.last < TIMESTAMP_MAX
    assert v.check(command(genuine), 0.0) is Verdict.OK


def test_far_future_timestamps_are_refused_when_the_clock_is_set():
    """A genuine sender whose clock runs a day ahead would otherwise move our clock forward and make its
    own later (correct) frames look replayed."""
    ahead = command(packer(ts=T0 + 86400 * TICKS_PER_S))
    v = verifier(max_future_s=600.0)
    assert v.check(ahead, 0.0) is Verdict.FUTURE
    assert v.clock.last < T0 + 700 * TICKS_PER_S and not v.streams
    assert v.check(command(packer()), 0.0) is Verdict.OK
    unset = Verifier(KEY, SigningClock(epoch=0, clock_set=False))  # no clock: nothing to compare with
    assert unset.check(ahead, 0.0) is Verdict.OK


def test_reorder_window_accepts_each_frame_once():
    p = packer()
    a, b, c = command(p), command(p), command(p)
    strict, windowed = verifier(), verifier(window=8)
    assert [strict.check(f, 0.0) for f in (a, c, b)] == [Verdict.OK, Verdict.OK, Verdict.REPLAY]
    assert [windowed.check(f, 0.0) for f in (a, c, b, b, a)] == [Verdict.OK, Verdict.OK, Verdict.OK,
                                                                  Verdict.REPLAY, Verdict.REPLAY]


def test_outgoing_signing_is_strictly_increasing_and_verifiable():
    clock = SigningClock(epoch=T0)
    p = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
    setup_outgoing(p, KEY, clock)
    v = verifier()
    stamps = []
    for _ in range(5):
        from fsw.telemetry.signing import sign_ready
        sign_ready(p, clock, now_s=0.0)  # the loop time does not move: timestamps still grow
        frame = mavlink.MAVLink_heartbeat_message(0, 0, 0, 0, 0, 3).pack(p)
        stamps.append(signature_fields(frame)[3])
        assert v.check(frame, 0.0) is Verdict.OK
    assert all(b > a for a, b in zip(stamps, stamps[1:]))


def test_sign_frame_builds_a_frame_pymavlink_accepts():
    frame = sign_frame(KEY, command(packer(key=None)), 3, T0 + 7)
    rx = mavlink.MAVLink(None)
    msg = rx.parse_buffer(frame)[0]
    assert msg.get_type() == "COMMAND_LONG" and msg.param7 == 7
    assert signature_fields(frame)[2:] == (3, T0 + 7)
    assert verifier().check(frame, 0.0) is Verdict.OK


def test_key_file_is_private_and_never_printed(tmp_path, capsys):
    path = tmp_path / "mission.key"
    assert keys.main(["new", str(path)]) == 0
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    key = load_key(path)
    assert len(key) == 32
    out = capsys.readouterr()
    assert key.hex() not in out.out + out.err and key.hex()[:8] not in out.out + out.err
    assert keys.main(["new", str(path)]) == 1                   # never overwritten silently
    assert load_key(path) == key
    assert keys.main(["new", str(path), "--force"]) == 0 and load_key(path) != key
    assert keys.main(["fingerprint", str(path)]) == 0


def test_bad_key_files_are_refused(tmp_path):
    readable = tmp_path / "open.key"
    write_key(readable, KEY)
    os.chmod(readable, 0o644)
    with pytest.raises(KeyFileError, match="accessible by others"):
        load_key(readable)
    short = tmp_path / "short.key"
    fd = os.open(short, os.O_WRONLY | os.O_CREAT, 0o600)
    os.write(fd, b"abcd\n")
    os.close(fd)
    with pytest.raises(KeyFileError, match="2 bytes"):
        load_key(short)
    with pytest.raises(KeyFileError, match="cannot read"):
        load_key(tmp_path / "missing.key")


@pytest.mark.parametrize("tail, ok", [(b"", True), (b" " * (KEY_FILE_MAX_BYTES - 65), True),
                                      (b" " * (KEY_FILE_MAX_BYTES - 64), False),
                                      (b" " * 5000 + b"not a key", False)],
                         ids=["key", "at the limit", "a byte more", "anything after"])
def test_a_key_file_longer_than_the_limit_is_refused(tmp_path, tail, ok):
    """Found by the fuzz (tests/test_fuzz_readers.py): only the first KEY_FILE_MAX_BYTES + 1 bytes were
    read, so a key followed by anything at all was accepted."""
    path = tmp_path / "long.key"
    path.write_bytes(KEY.hex().encode() + b"\n" + tail)
    path.chmod(0o600)
    if ok:
        assert load_key(path) == KEY
    else:
        with pytest.raises(KeyFileError, match=f"more than {KEY_FILE_MAX_BYTES} bytes"):
            load_key(path)
