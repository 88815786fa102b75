"""Output to a reader that has gone (`… | head -1`): the flight loop flies on, a command line ends with
one exit status and no traceback (`fsw.startup.exit_with`, `fsw.runner.run_loop`)."""
import io
import subprocess
import sys

import pytest

from fsw.startup import BROKEN_PIPE_STATUS
from hil import sitl

pytestmark = pytest.mark.sitl


class ClosedPipe(io.StringIO):
    """A stream whose reader went away after the first thing printed on it."""

    def write(self, s: str) -> int:
        if self.getvalue().endswith("\n"):
            raise BrokenPipeError(32, "Broken pipe")
        return super().write(s)


def test_the_loop_flies_on_when_its_status_lines_reader_goes():
    run = sitl.run(sitl.parse_args(["--duration", "6", "--speed", "0"]), out=ClosedPipe())
    assert run.loop.t_s == pytest.approx(6.0)      # the whole run, not stopped at the first status line
    assert run.loop.status_lost
    assert run.fsw.samples >= 6                    # the magnetometer was read throughout (1 Hz)


def test_a_command_line_into_a_closed_pipe_ends_quietly():
    p = subprocess.Popen([sys.executable, "-m", "hil.sitl", "--duration", "8", "--speed", "0"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    p.stdout.readline()
    p.stdout.close()                               # `| head -1`
    err = p.stderr.read().decode()
    assert p.wait(timeout=120) == BROKEN_PIPE_STATUS
    assert "Traceback" not in err and "Exception ignored" not in err and "error" not in err, err
