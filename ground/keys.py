"""Mission keys for MAVLink 2 signing.

    python -m ground.keys new FILE [--force]     create a key (32 random bytes), file mode 0600
    python -m ground.keys fingerprint FILE       show the key's fingerprint (not the key)

The key itself is never printed. A new key is created exclusively; `--force` replaces only a regular
file (atomically), never a symbolic link, FIFO or device (`fsw.telemetry.signing.write_key`); reading
never waits on a FIFO (`load_key`). The same file goes to the flight computer (`python -m fsw.main
--key FILE`) and to the ground tools (`--key FILE`); docs/ground.md, "Mission keys", explains
provisioning, docs/link-and-security.md what the key protects.
"""
from __future__ import annotations

import secrets
import sys

from fsw.argtypes import ArgumentParser, check_paths_or_exit
from fsw.telemetry.signing import KEY_BYTES, KeyFileError, key_fingerprint, load_key, write_key


def new_key(path: str, *, overwrite: bool = False) -> str:
    """Create a key file at `path` from the OS's cryptographic random source; returns its fingerprint."""
    key = secrets.token_bytes(KEY_BYTES)
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
    args = ap.parse_args(argv)
    if args.action == "new":
        check_paths_or_exit(ap, outputs={"": args.file})
    try:
        if args.action == "new":
            fp = new_key(args.file, overwrite=args.force)
            print(f"wrote {args.file} (mode 0600), key fingerprint {fp}")
        else:
            print(key_fingerprint(load_key(args.file)))
    except FileExistsError:
        print(f"ground.keys: {args.file} exists (use --force to replace it)", file=sys.stderr)
        return 1
    except (OSError, KeyFileError) as e:
        print(f"ground.keys: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    from fsw.startup import exit_with

    exit_with(main)
