"""python -m ground.archive: what the archive holds, and an interval of a box out of it.

    python -m ground.archive list [--archive FILE] [--gap S]
    python -m ground.archive export --box SYSID [--from T] [--to T] [--csv FILE] [--rates-csv FILE]
                                    [--method M] [--tlog FILE] [--archive FILE]
    python -m ground.archive prune --box SYSID --before T (--tlog FILE | --discard) [--archive FILE]

``list``: every source (sysid/compid), its stretches of reception (split where nothing came for more
than ``--gap`` seconds, default 60) with their UTC times and frame counts.

``export``: box SYSID's frames received from ``--from`` (included) to ``--to`` (excluded), each a UTC
time in ISO 8601 (``2026-11-24T10:00:00Z``, ``2026-11-24 10:00``; a time without a zone is UTC) or
seconds since 1970; either left out: from the first frame / to the last. ``--tlog``: the frames as
received; ``--csv`` / ``--rates-csv`` (of ``--method``): the recordings `ground.decode --csv` / ``--rates-csv`` writes
(`ground.archive.export`). Output paths are checked first (`fsw.files.check_paths`: none may be the
archive). Nothing in the interval: said, nothing written, exit status 1. The archive is read as one
snapshot, so exporting while a station writes is safe.

``prune``: box SYSID's frames received before ``--before`` deleted from the archive, never silently: with
``--tlog FILE`` they are first written there (as ``export --tlog``), ``--discard`` says they may go without a
copy; one of the two is required. It says how many frames it deleted and their first and last time
(`ground.archive.retention`: a station may write the archive meanwhile).
"""
from __future__ import annotations

import argparse
import math
import sys
from datetime import datetime, timezone

from fsw.argtypes import ArgumentParser, check_paths_or_exit, finite_float, int_range

from ..decode import METHODS
from .export import export_recordings, export_tlog
from .retention import prune
from .store import ArchiveError, default_path, open_reader, spans


def utc_time_us(text: str) -> int:
    """µs since 1970 of an ISO 8601 UTC time (no zone: UTC) or of seconds since 1970 (ValueError if neither)."""
    try:
        seconds = float(text)
    except ValueError:
        seconds = None
    if seconds is not None and math.isfinite(seconds) and abs(seconds) < 1e11:
        return round(seconds * 1e6)
    try:
        when = datetime.fromisoformat(text.strip())
    except ValueError:
        raise ValueError(f"not a time: {text!r} (ISO 8601 UTC, e.g. 2026-11-24T10:00:00Z, or seconds since "
                         "1970)") from None
    if when.tzinfo is None:
        when = when.replace(tzinfo=timezone.utc)
    return round(when.timestamp() * 1e6)


def _time_arg(text: str) -> int:
    try:
        return utc_time_us(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _utc(t_us: int) -> str:
    return datetime.fromtimestamp(t_us // 1_000_000, tz=timezone.utc).strftime("%Y-%m-%dT%H:%M:%S") + \
        f".{t_us % 1_000_000 // 1000:03d}Z"


def main(argv: list[str] | None = None) -> int:
    ap = ArgumentParser(prog="python -m ground.archive", description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True)
    ls = sub.add_parser("list", help="sources, stretches of reception and frame counts")
    ex = sub.add_parser("export", help="an interval of one box as a .tlog and/or recordings")
    pr = sub.add_parser("prune", help="a box's frames before a time out of the archive (kept in a .tlog, or discarded)")
    for p in (ls, ex, pr):
        p.add_argument("--archive", default=str(default_path()),
                       help=f"the archive (default {default_path()})")
    ls.add_argument("--gap", type=finite_float(0, min_exclusive=True), default=60.0, metavar="S",
                    help="a stretch ends where nothing came for longer than this (s, default 60)")
    ex.add_argument("--box", type=int_range(1, 255), required=True, metavar="SYSID", help="the box's system id")
    ex.add_argument("--from", dest="from_us", type=_time_arg, metavar="T",
                    help="first receive time (included): ISO 8601 UTC or seconds since 1970")
    ex.add_argument("--to", dest="to_us", type=_time_arg, metavar="T", help="last receive time (excluded)")
    ex.add_argument("--csv", help="the magnetometer samples as recording-format CSV (as ground.decode --csv)")
    ex.add_argument("--rates-csv", help="the onboard rate estimates of --method as CSV (as ground.decode --rates-csv)")
    ex.add_argument("--method", choices=sorted(METHODS, key=METHODS.get), default="boer",
                    help="the onboard estimator of --rates-csv (default boer)")
    ex.add_argument("--tlog", help="the frames as received, as a .tlog")
    pr.add_argument("--box", type=int_range(1, 255), required=True, metavar="SYSID", help="the box's system id")
    pr.add_argument("--before", dest="before_us", type=_time_arg, required=True, metavar="T",
                    help="frames received before this time (excluded): ISO 8601 UTC or seconds since 1970")
    how = pr.add_mutually_exclusive_group()
    how.add_argument("--tlog", help="write the frames deleted to this .tlog first")
    how.add_argument("--discard", action="store_true", help="delete them without keeping a copy")
    args = ap.parse_args(argv)
    archive = args.archive
    inputs = {"--archive": archive, "the archive's journal": archive + "-wal", "the archive's index": archive + "-shm"}
    if args.command == "export":
        if not (args.csv or args.rates_csv or args.tlog):
            ap.error("export: give --csv, --rates-csv and/or --tlog")
        if args.from_us is not None and args.to_us is not None and args.to_us <= args.from_us:
            ap.error("export: --to must be after --from")
        check_paths_or_exit(ap, inputs=inputs,
                            outputs={"--csv": args.csv, "--rates-csv": args.rates_csv, "--tlog": args.tlog})
    if args.command == "prune":
        if not (args.tlog or args.discard):
            ap.error("prune: give --tlog FILE to keep a copy of the frames deleted, or --discard")
        check_paths_or_exit(ap, inputs=inputs, outputs={"--tlog": args.tlog})
    try:
        conn = open_reader(archive)
    except ArchiveError as e:
        ap.error(str(e))
    if args.command == "prune":
        conn.close()
        return _prune(args)
    try:
        if args.command == "list":
            found = spans(conn, args.gap)
            if not found:
                print(f"{archive}: empty")
            for s in found:
                print(f"box {s.sysid}/{s.compid}: {_utc(s.first_us)} to {_utc(s.last_us)}  "
                      f"({(s.last_us - s.first_us) * 1e-6:.1f} s, {s.frames} frames)")
            return 0
        return _export(conn, args)
    finally:
        conn.close()


def _export(conn, args) -> int:
    shown = f"box {args.box}" + (f" from {_utc(args.from_us)}" if args.from_us is not None else "") + \
        (f" to {_utc(args.to_us)}" if args.to_us is not None else "")
    done = []
    if args.tlog:
        out = export_tlog(conn, args.box, args.tlog, args.from_us, args.to_us)
        if not out.frames:
            print(f"ground.archive: no frames of {shown} in {args.archive}", file=sys.stderr)
            return 1
        done += out.written
        print(f"{out.frames} frames of box {args.box}, {_utc(out.first_us)} to {_utc(out.last_us)}")
    if args.csv or args.rates_csv:
        out = export_recordings(conn, args.box, args.csv, args.rates_csv, args.from_us, args.to_us,
                                method=METHODS[args.method],
                                origin=f"{args.archive} ({shown})", protect=[args.archive] + (
                                    [args.tlog] if args.tlog else []))
        if not out.frames:
            print(f"ground.archive: no frames of {shown} in {args.archive}", file=sys.stderr)
            return 1
        if not args.tlog:
            print(f"{out.frames} frames of box {args.box}, {_utc(out.first_us)} to {_utc(out.last_us)}")
        if not out.written:
            print("no magnetometer samples in the interval: no recording written")
        done += out.written
    for what, path in done:
        print(f"wrote {what}: {path}")
    return 0


def _prune(args) -> int:
    try:
        out = prune(args.archive, args.box, args.before_us, args.tlog)
    except ArchiveError as e:
        print(f"ground.archive: {e}", file=sys.stderr)
        return 1
    if not out.frames:
        print(f"no frames of box {args.box} before {_utc(args.before_us)} in {args.archive}: nothing deleted")
        return 0
    where = f"kept in {out.kept}" if out.kept else "discarded, no copy kept (--discard)"
    print(f"deleted {out.frames} frames of box {args.box} received {_utc(out.first_us)} to {_utc(out.last_us)}: "
          f"{where}")
    return 0


if __name__ == "__main__":
    from fsw.startup import exit_with

    exit_with(main)
