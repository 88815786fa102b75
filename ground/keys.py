"""Mission keys for MAVLink 2 signing.

    python -m ground.keys new FILE [--force]     create a key (32 random bytes), file mode 0600
    python -m ground.keys fingerprint FILE       show the key's fingerprint (not the key)
    python -m ground.keys from-passphrase FILE   the key MAVProxy makes of a passphrase (read from
                                                 the terminal, asked twice, or one line of stdin)

The key itself is never printed. A new key is created exclusively; `--force` replaces only a regular
file (atomically), never a symbolic link, FIFO or device (`fsw.telemetry.signing.write_key`); reading
never waits on a FIFO (`load_key`). The same file goes to the flight computer (`python -m fsw.main
--key FILE`) and to the ground tools (`--key FILE`); docs/ground.md, "Mission keys", explains
provisioning, docs/link-and-security.md what the key protects.

`from-passphrase`: MAVProxy's ``signing setup PASSPHRASE`` / ``signing key PASSPHRASE`` sign with
SHA-256 of the passphrase's ASCII bytes (MAVProxy/modules/mavproxy_signing.py, `passphrase_to_key`);
the same 32 bytes written as a key file make the box and the project's ground tools accept what a stock
MAVProxy with that passphrase signs. The passphrase is never an argument: a command line is kept in the
shell's history and shown to every user by `ps` while the program runs. It is read from the terminal
without echo (twice, to catch a typo) or, from a pipe, as one line of stdin. MAVProxy splits its
commands (and its ~/.mavproxy/signing.keys lines) on white space and encodes ASCII, so a passphrase
with a space or a non-ASCII character could not be typed there: refused, as is one shorter than
`MIN_PASSPHRASE_CHARS` (the key is only as hard to guess as the passphrase).
"""
from __future__ import annotations

import getpass
import hashlib
import secrets
import sys

from fsw.argtypes import ArgumentParser, check_paths_or_exit
from fsw.telemetry.signing import KEY_BYTES, KeyFileError, key_fingerprint, load_key, write_key


def new_key(path: str, *, overwrite: bool = False) -> str:
    """Create a key file at `path` from the OS's cryptographic random source; returns its fingerprint."""
    key = secrets.token_bytes(KEY_BYTES)
    write_key(path, key, overwrite=overwrite)
    return key_fingerprint(key)


#: the shortest passphrase taken (a key is only as hard to guess as its passphrase: prefer 20+ characters)
MIN_PASSPHRASE_CHARS = 12


class PassphraseError(ValueError):
    """A passphrase MAVProxy could not use, or too short to be a secret."""


def passphrase_key(passphrase: str) -> bytes:
    """MAVProxy's key of `passphrase`: SHA-256 of its ASCII bytes (checked: printable ASCII, no white
    space, at least `MIN_PASSPHRASE_CHARS` characters)."""
    if len(passphrase) < MIN_PASSPHRASE_CHARS:
        raise PassphraseError(f"passphrase has {len(passphrase)} characters, at least {MIN_PASSPHRASE_CHARS} needed")
    if not all(33 <= ord(ch) <= 126 for ch in passphrase):
        raise PassphraseError("passphrase must be printable ASCII without spaces (MAVProxy splits its "
                              "commands on white space and encodes ASCII)")
    return hashlib.sha256(passphrase.encode("ascii")).digest()


def read_passphrase(stdin=None) -> str:
    """From the terminal without echo, asked twice; from a pipe or file, its first line (no newline)."""
    stdin = sys.stdin if stdin is None else stdin
    if stdin.isatty():
        first = getpass.getpass("passphrase: ")
        if getpass.getpass("again: ") != first:
            raise PassphraseError("the two passphrases differ")
        return first
    line = stdin.readline(4096)
    return line[:-1] if line.endswith("\n") else line


def key_from_passphrase(path: str, passphrase: str, *, overwrite: bool = False) -> str:
    """Write MAVProxy's key of `passphrase` as a key file at `path` (mode 0600); returns its fingerprint."""
    key = passphrase_key(passphrase)
    write_key(path, key, overwrite=overwrite)
    return key_fingerprint(key)


def main(argv: list[str] | None = None) -> int:
    ap = ArgumentParser(prog="python -m ground.keys", description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="action", required=True)
    n = sub.add_parser("new", help="create a new key file (mode 0600)")
    n.add_argument("file")
    n.add_argument("--force", action="store_true", help="replace an existing file")
    f = sub.add_parser("fingerprint", help="print the fingerprint of a key file")
    f.add_argument("file")
    p = sub.add_parser("from-passphrase", help="write the key MAVProxy's `signing key PASSPHRASE` uses "
                       "(the passphrase is read from the terminal or stdin, never from the command line)")
    p.add_argument("file")
    p.add_argument("--force", action="store_true", help="replace an existing file")
    args = ap.parse_args(argv)
    if args.action in ("new", "from-passphrase"):
        check_paths_or_exit(ap, outputs={"": args.file})
    try:
        if args.action == "new":
            fp = new_key(args.file, overwrite=args.force)
            print(f"wrote {args.file} (mode 0600), key fingerprint {fp}")
        elif args.action == "from-passphrase":
            fp = key_from_passphrase(args.file, read_passphrase(), overwrite=args.force)
            print(f"wrote {args.file} (mode 0600), key fingerprint {fp}")
        else:
            print(key_fingerprint(load_key(args.file)))
    except FileExistsError:
        print(f"ground.keys: {args.file} exists (use --force to replace it)", file=sys.stderr)
        return 1
    except (OSError, KeyFileError, PassphraseError) as e:
        print(f"ground.keys: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    from fsw.startup import exit_with

    exit_with(main)
