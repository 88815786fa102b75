"""Ctrl-C while a program's modules load: one line and exit status 130, no traceback.

Loading numpy, numba and the compiled estimators takes a second or more. A program's entry module
calls :func:`interrupt_quietly` before those imports; the first thing its `main` does after them is
to leave the signal to the loop (`fsw.runner`). An exception raised in a signal handler could land
inside a compiled module's initialisation, which would turn it into an ImportError with a traceback,
so the handler ends the process at once: nothing is open yet that needs closing.
"""
from __future__ import annotations

import os
import signal
import sys


def _interrupted(signum, frame) -> None:
    print("interrupted", file=sys.stderr, flush=True)
    os._exit(130)


def interrupt_quietly() -> None:
    signal.signal(signal.SIGINT, _interrupted)
