"""State files that survive a restart: whole or not at all, never a torn one.

A state file is one JSON document:

    {"format": "debris-box-state", "version": 1, "kind": "signing", "sha256": "...", "payload": {...}}

`sha256` is the digest of the payload's canonical JSON (sorted keys, no spaces). :func:`save_state`
writes through `fsw.files.write_atomic` (a temporary file in the same directory, flushed, fsync'ed,
renamed over the old one) and then fsyncs the directory, so that after a power cut the name points at
either the old file or the new one. :func:`load_state` refuses, with the reason, a file that is missing,
not JSON, of another kind or version, or whose digest does not match its payload (a torn or corrupted
file: a crash of a file system that reordered writes, a manual edit, a bad sector), so a torn file is
never loaded; a leftover temporary file (``.NAME.*.tmp``, a crash mid-write) is never read.
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from .files import write_atomic

FORMAT = "debris-box-state"
VERSION = 1
MAX_BYTES = 1 << 20


def _digest(payload) -> str:
    return hashlib.sha256(json.dumps(payload, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def save_state(path: str | os.PathLike, kind: str, payload: dict) -> None:
    """Write `payload` as the state file `path` of `kind`, atomically and durably (OSError if it cannot)."""
    doc = {"format": FORMAT, "version": VERSION, "kind": kind, "sha256": _digest(payload), "payload": payload}
    path = Path(path)
    write_atomic(path, json.dumps(doc, sort_keys=True, indent=1) + "\n", permissions=0o600)
    fd = os.open(path.parent, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def load_state(path: str | os.PathLike, kind: str) -> tuple[dict | None, str]:
    """(payload, "") of a good state file of `kind`, else (None, why it was not loaded)."""
    try:
        with open(path, "rb") as f:
            raw = f.read(MAX_BYTES + 1)
    except FileNotFoundError:
        return None, "none saved"
    except OSError as e:
        return None, f"unreadable: {e.strerror or e}"
    if len(raw) > MAX_BYTES:
        return None, "larger than a state file can be"
    try:
        doc = json.loads(raw)
    except (UnicodeDecodeError, json.JSONDecodeError):
        return None, "not a whole state file (torn or corrupted): ignored"
    if not isinstance(doc, dict) or doc.get("format") != FORMAT or doc.get("kind") != kind:
        return None, f"not a {kind} state file: ignored"
    if doc.get("version") != VERSION:
        return None, f"version {doc.get('version')!r}, not {VERSION}: ignored"
    payload = doc.get("payload")
    if not isinstance(payload, dict) or doc.get("sha256") != _digest(payload):
        return None, "checksum does not match (torn or corrupted): ignored"
    return payload, ""
