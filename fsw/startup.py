"""How every command line starts and ends: Ctrl-C while its modules load, and output to a reader that
has gone.

Ctrl-C while a program's modules load: one line and exit status 130, no traceback.

Loading numpy, numba and the compiled estimators takes a second or more. A program's entry module
calls :func:`interrupt_quietly` before those imports; the first thing its `main` does after them is
to leave the signal to the loop (`fsw.runner`). An exception raised in a signal handler could land
inside a compiled module's initialisation, which would turn it into an ImportError with a traceback,
so the handler ends the process at once: nothing is open yet that needs closing.

Output to a pipe whose reader has gone (`python -m ground.command --list | head -1`): the program ends
quietly with exit status 141 (128 + SIGPIPE, what a shell reports for a tool killed by the signal),
without a traceback and without Python's own complaint at exit about the stream it could not flush.
The flight loop itself never stops for it: its status lines stop (`fsw.runner.run_loop`).
"""
from __future__ import annotations

import os
import signal
import sys
from typing import Callable, NoReturn


def _interrupted(signum, frame) -> None:
    print("interrupted", file=sys.stderr, flush=True)
    os._exit(130)


def interrupt_quietly() -> None:
    signal.signal(signal.SIGINT, _interrupted)


#: exit status of a program whose standard output's reader went away
BROKEN_PIPE_STATUS = 128 + signal.SIGPIPE


def exit_with(main: Callable[[], int | None]) -> NoReturn:
    """`sys.exit(main())`, ending quietly with :data:`BROKEN_PIPE_STATUS` when stdout's reader has gone."""
    try:
        status = main()
        sys.stdout.flush()
    except BrokenPipeError:
        # what is still buffered can never be written: point stdout at /dev/null so that the
        # interpreter's flush at exit does not complain
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        status = BROKEN_PIPE_STATUS
    sys.exit(status)
