"""`python -m ground.keys from-passphrase FILE`: the key MAVProxy's `signing key PASSPHRASE` signs with
(SHA-256 of the passphrase, MAVProxy/modules/mavproxy_signing.py), as a key file the box accepts."""
import io
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from fsw.telemetry.dialect import mavlink
from fsw.telemetry.signing import SigningClock, Verdict, Verifier, load_key, unix_to_timestamp
from ground import keys

ROOT = Path(__file__).resolve().parents[2]
PASSPHRASE = "correct-horse-battery"
#: `printf %s correct-horse-battery | sha256sum` (coreutils), not Python's hashlib
KEY_HEX = "62249369389075490555a758353aec61500c6218fa597252d52dc4bd0148f12d"


def run_keys(*argv, stdin=""):
    return subprocess.run([sys.executable, "-m", "ground.keys", *argv], cwd=ROOT, input=stdin,
                          capture_output=True, text=True, timeout=60)


def test_the_key_is_sha256_of_the_passphrase_from_stdin_never_an_argument(tmp_path):
    out = tmp_path / "mission.key"
    r = run_keys("from-passphrase", str(out), stdin=PASSPHRASE + "\n")
    assert r.returncode == 0, r.stderr
    assert PASSPHRASE not in r.stdout + r.stderr  # never echoed
    assert load_key(out).hex() == KEY_HEX
    assert stat.S_IMODE(out.stat().st_mode) == 0o600
    assert keys.passphrase_key(PASSPHRASE).hex() == KEY_HEX


def test_a_frame_pymavlink_signs_with_the_passphrase_key_is_accepted_by_the_box(tmp_path):
    """MAVProxy signs through pymavlink's MAVLink.signing with that key: the box's verifier accepts it."""
    out = tmp_path / "mission.key"
    keys.key_from_passphrase(str(out), PASSPHRASE)
    gcs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    gcs.signing.secret_key = bytes.fromhex(KEY_HEX)  # as MAVProxy's setup_signing sets it
    gcs.signing.sign_outgoing = True
    gcs.signing.timestamp = unix_to_timestamp(1.8e9)
    frame = mavlink.MAVLink_ping_message(1, 0, 0, 0).pack(gcs)
    verifier = Verifier(load_key(out), SigningClock(epoch=unix_to_timestamp(1.8e9)))
    assert verifier.check(frame, 0.0) is Verdict.OK
    other = Verifier(keys.passphrase_key(PASSPHRASE + "x"), SigningClock(epoch=unix_to_timestamp(1.8e9)))
    assert other.check(frame, 0.0) is Verdict.BAD_SIGNATURE


@pytest.mark.parametrize("phrase, words", [("short", "at least"), ("has a space in it", "without spaces"),
                                           ("caf\u00e9-au-lait-noir", "ASCII"), ("", "at least")])
def test_passphrases_mavproxy_could_not_use_are_refused_in_one_line(tmp_path, phrase, words):
    out = tmp_path / "mission.key"
    r = run_keys("from-passphrase", str(out), stdin=phrase + "\n")
    assert r.returncode == 1 and "Traceback" not in r.stderr
    assert words in r.stderr.strip().splitlines()[-1]
    assert not out.exists()


def test_an_existing_key_file_is_kept_unless_force(tmp_path):
    out = tmp_path / "mission.key"
    keys.new_key(str(out))
    before = out.read_bytes()
    r = run_keys("from-passphrase", str(out), stdin=PASSPHRASE + "\n")
    assert r.returncode == 1 and "exists" in r.stderr and out.read_bytes() == before
    r = run_keys("from-passphrase", str(out), "--force", stdin=PASSPHRASE + "\n")
    assert r.returncode == 0 and load_key(out).hex() == KEY_HEX


def test_the_terminal_asks_twice_and_refuses_a_mismatch(monkeypatch):
    class Tty(io.StringIO):
        def isatty(self):
            return True

    answers = iter([PASSPHRASE, PASSPHRASE + "!"])
    monkeypatch.setattr(keys.getpass, "getpass", lambda prompt="": next(answers))
    with pytest.raises(keys.PassphraseError, match="differ"):
        keys.read_passphrase(Tty())
