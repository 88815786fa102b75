"""State files (fsw.state_files): whole or not at all; a torn, corrupted or foreign file never loaded."""
import json
import os
import stat

import pytest

from fsw.state_files import load_state, save_state

PAYLOAD = {"clock_last": 123456789, "streams": [[255, 190, 0, 123456000]]}


def test_saved_and_loaded(tmp_path):
    path = tmp_path / "signing.json"
    save_state(path, "signing", PAYLOAD)
    assert load_state(path, "signing") == (PAYLOAD, "")
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o600
    assert [p.name for p in tmp_path.iterdir()] == ["signing.json"]  # no temporary file left


@pytest.mark.parametrize("cut", [1, 20, 60, -2])
def test_a_torn_file_is_never_loaded(tmp_path, cut):
    path = tmp_path / "signing.json"
    save_state(path, "signing", PAYLOAD)
    raw = path.read_bytes()
    path.write_bytes(raw[:cut])
    payload, why = load_state(path, "signing")
    assert payload is None and "ignored" in why


def test_a_changed_payload_fails_its_checksum(tmp_path):
    path = tmp_path / "signing.json"
    save_state(path, "signing", PAYLOAD)
    doc = json.loads(path.read_text())
    doc["payload"]["streams"][0][3] -= 1000  # an older timestamp written in by hand (or a bad sector)
    path.write_text(json.dumps(doc))
    assert load_state(path, "signing") == (None, "checksum does not match (torn or corrupted): ignored")


def test_missing_foreign_and_other_versions(tmp_path):
    assert load_state(tmp_path / "none.json", "signing") == (None, "none saved")
    path = tmp_path / "time.json"
    save_state(path, "time", {"utc_s": 1.0})
    assert load_state(path, "signing")[0] is None
    doc = json.loads(path.read_text())
    doc["version"] = 2
    path.write_text(json.dumps(doc))
    assert "version" in load_state(path, "time")[1]
    path.write_bytes(b"\xff\xfe")
    assert load_state(path, "time")[0] is None


def test_a_crash_mid_write_leaves_the_old_file(tmp_path, monkeypatch):
    path = tmp_path / "signing.json"
    save_state(path, "signing", PAYLOAD)

    def crash(fd):
        raise OSError(5, "Input/output error")
    monkeypatch.setattr(os, "fsync", crash)
    with pytest.raises(OSError):
        save_state(path, "signing", {"clock_last": 1, "streams": []})
    monkeypatch.undo()
    assert load_state(path, "signing") == (PAYLOAD, "")
    assert [p.name for p in tmp_path.iterdir()] == ["signing.json"]
