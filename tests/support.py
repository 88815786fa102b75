"""Helpers shared by the test modules (importable from tests/ and its sub-directories: tests/conftest.py
puts this directory on the path)."""
import socket

from fsw.telemetry.dialect import FSW_COMPID, FSW_SYSID, mavlink


def free_udp_port() -> int:
    """A UDP port on the loopback that is free now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class NullLink:
    """A telemetry connection that packs with the flight software's ids, counts bytes and drops them."""

    def __init__(self):
        self.mav = mavlink.MAVLink(self, srcSystem=FSW_SYSID, srcComponent=FSW_COMPID)
        self.bytes = 0

    def write(self, b):
        self.bytes += len(b)


def exit_status(main, argv) -> int:
    """A tool's exit status from its `main(argv)`, whether it returns it or argparse exits with it."""
    try:
        return main(argv)
    except SystemExit as e:
        return e.code if isinstance(e.code, int) else 1


def tiers(prop, *strategies, **kw_strategies):
    """A property (a function of the drawn values) as its two tests: the fast one, with the loaded
    hypothesis profile (conftest.py: 200 examples, or 10,000 with HYPOTHESIS_PROFILE=fuzz), and the
    slow tier's, marked ``slow``, with the ``fuzz`` profile (10,000 examples)::

        test_reader, test_reader_fuzz = tiers(reader_property, inputs())
    """
    import pytest
    from hypothesis import given, settings

    fast = given(*strategies, **kw_strategies)(prop)
    slow = settings(settings.get_profile("fuzz"))(given(*strategies, **kw_strategies)(prop))
    return fast, pytest.mark.slow(slow)
