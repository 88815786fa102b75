"""The telemetry archive: every intact frame the ground station receives, kept in an SQLite file per
box and receive time, and any interval of a box exported as a .tlog or as recordings.

    python -m ground.archive list [--archive FILE] [--gap S]
    python -m ground.archive export --box SYSID [--from T] [--to T] [--csv FILE] [--rates-csv FILE]
                                    [--method M] [--tlog FILE] [--archive FILE]

`ground.decode` archives every intact frame it receives from a live link by default
(`--archive FILE`, default `store.default_path`; `--no-archive`); from a .tlog only when asked.

Why SQLite: it is in Python's standard library (no new dependency), one file, made for this many small
appends (a row per frame, in transactions of half a second), and its WAL mode is exactly the two
guarantees asked for: a crash or a power cut loses at most the last transaction not yet committed (the
frames of the last second: `store`), and any number of readers (a second station, an export) read a
consistent snapshot while the station writes. DuckDB (columnar, for analytical queries over many
rows) would be a new dependency, is slower at row-by-row appends and allows one process at a time on a
file; the archive's reads are ranges of one box in time, which SQLite's index answers directly.

- `store`: the file (layout, writer, reader);
- `export`: an interval as a .tlog or as `ground.decode`'s recordings;
- `__main__`: the command line.
"""
from .store import ArchiveError, ArchiveWriter, default_path, open_reader

__all__ = ["ArchiveError", "ArchiveWriter", "default_path", "open_reader"]
