"""Output files: checked before any work, written atomically, never over an input.

:func:`check_paths` is what every tool calls at start, before it opens a link, reads a recording or
runs a fit, so that a bad output path fails in the first second and not after the work. It refuses,
with a one-line :class:`PathError` naming the paths:

- an output that is the same file as an input, or as another output: the same (st_dev, st_ino) for
  files that exist (so hard links and symbolic links are caught), the same resolved path
  (`os.path.realpath`, symbolic links in the directories followed) for files not created yet;
- an output whose directory does not exist, is not a directory or is not writable;
- an output that exists and is a directory, a FIFO, a device or a socket, or is not writable;
- an empty path, input or output (``--key ""`` from an unset shell variable is not "no key").

:func:`atomic_file` / :func:`write_atomic` write through a temporary file in the same directory that
replaces the target only when complete (`os.replace`): a crash or an error leaves the old file, or no
file, never half of one. An output that is a symbolic link is replaced by the new file, never written
through. A replaced file keeps its permissions; new files get those the umask gives (or `permissions`).
"""
from __future__ import annotations

import contextlib
import os
import stat
import tempfile
from pathlib import Path
from typing import Iterable, Iterator, Mapping

PathLike = str | os.PathLike


class PathError(ValueError):
    """An output path that cannot be used; the message names it (and the other path involved)."""


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_DEFAULT_MODE = 0o666 & ~_umask()


def _pairs(paths: Mapping[str, PathLike | None] | Iterable[tuple[str, PathLike | None]]
           ) -> list[tuple[str, str]]:
    """(label, path) of the paths given (None: not given); an empty path is refused: it names no file,
    and a tool that took it for "not given" would quietly do something else (run without a key)."""
    items = paths.items() if isinstance(paths, Mapping) else paths
    out = []
    for label, p in items:
        if p is None:
            continue
        if os.fspath(p) == "":
            raise PathError(f"{label or 'path'}: empty path")
        out.append((label, os.fspath(p)))
    return out


def _identity(path: str) -> tuple:
    """(device, inode) of an existing file (symbolic links followed), else its resolved path."""
    try:
        st = os.stat(path)
    except OSError:
        return ("path", os.path.realpath(path))
    return ("inode", st.st_dev, st.st_ino)


def _named(label: str, path: str) -> str:
    return path if label in ("", path) else f"{label} {path}"


def check_output(label: str, path: str) -> None:
    """Refuse an output path that cannot be written as a regular file (see the module docstring)."""
    shown = _named(label, path)
    try:
        st = os.stat(path)
    except (FileNotFoundError, NotADirectoryError):
        st = None
    except OSError as e:
        raise PathError(f"{shown}: {e.strerror or e}") from None
    if st is not None:
        if stat.S_ISDIR(st.st_mode):
            raise PathError(f"{shown}: is a directory, not a file")
        if not stat.S_ISREG(st.st_mode):
            raise PathError(f"{shown}: is not a regular file (a FIFO, device or socket)")
        if not os.access(path, os.W_OK):
            raise PathError(f"{shown}: file is not writable")
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.exists(folder):
        raise PathError(f"{shown}: directory {folder} does not exist")
    if not os.path.isdir(folder):
        raise PathError(f"{shown}: {folder} is not a directory")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise PathError(f"{shown}: directory {folder} is not writable")


def check_paths(inputs: Mapping[str, PathLike | None] | Iterable[tuple[str, PathLike | None]] = (),
                outputs: Mapping[str, PathLike | None] | Iterable[tuple[str, PathLike | None]] = ()) -> None:
    """Refuse (PathError) outputs that are an input or another output, or cannot be written.

    `inputs` and `outputs` map a label (the option, e.g. ``"--csv"``, or ``"input"``) to a path;
    None entries are left out. Inputs that do not exist are left to the tool that reads them, but no
    output may take their name (a serial port not plugged in yet, an input file mistyped)."""
    ins = [(label, p, _identity(p)) for label, p in _pairs(inputs)]
    outs = _pairs(outputs)
    seen: list[tuple[str, str, tuple]] = []
    for label, p in outs:
        ident = _identity(p)
        for in_label, q, other in ins:
            if ident == other:
                raise PathError(f"{_named(label, p)} is the same file as {_named(in_label, q)}: "
                                "an output may not overwrite an input")
        for out_label, q, other in seen:
            if ident == other:
                raise PathError(f"{_named(out_label, q)} and {_named(label, p)} are the same file")
        seen.append((label, p, ident))
    for label, p in outs:
        check_output(label, p)


@contextlib.contextmanager
def atomic_file(path: PathLike, mode: str = "w", *, permissions: int | None = None,
                encoding: str | None = "utf-8", newline: str | None = "\n") -> Iterator:
    """A file object (`mode` "w" or "wb") whose content replaces `path` when the block ends without an
    exception (flushed, fsync'ed, `os.replace`); on an exception the temporary file is removed and
    `path` is left as it was. `permissions`: of the new file (default: those of the regular file it
    replaces, else 0666 less the umask)."""
    if mode not in ("w", "wb"):
        raise ValueError(f"mode must be 'w' or 'wb', not {mode!r}")
    path = Path(path)
    if permissions is None:
        try:
            st = os.lstat(path)
            permissions = stat.S_IMODE(st.st_mode) if stat.S_ISREG(st.st_mode) else _DEFAULT_MODE
        except OSError:
            permissions = _DEFAULT_MODE
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, permissions)
        text = {} if mode == "wb" else {"encoding": encoding, "newline": newline}
        with os.fdopen(fd, mode, **text) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def write_atomic(path: PathLike, data: str | bytes | Iterable[str], *, permissions: int | None = None) -> None:
    """Write `data` (bytes, text, or lines of text each written with a newline) to `path` atomically."""
    if isinstance(data, bytes):
        with atomic_file(path, "wb", permissions=permissions) as f:
            f.write(data)
        return
    with atomic_file(path, "w", permissions=permissions) as f:
        if isinstance(data, str):
            f.write(data)
        else:
            for line in data:
                f.write(line)
                f.write("\n")
