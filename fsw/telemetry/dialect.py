"""The project's MAVLink dialect: generated bindings and connections that use them.

`debris.xml` (beside this file) is the single definition of the project's telemetry. It includes
pymavlink's `common.xml`; pymavlink's mavgen turns it into `mavlink_debris.py`, which is committed and
kept in sync by a test (`tests/test_dialect.py`). Regenerate with `make dialect` after editing the XML.

MAVLink 2 only: every connection opened here speaks MAVLink 2 from its first frame.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")  # pymavlink's mavutil picks v2.0 bindings from this

from pymavlink import mavutil  # noqa: E402

from . import mavlink_debris as mavlink  # noqa: E402,F401  (re-exported: fsw.telemetry.dialect.mavlink)
from ..argtypes import ArgumentParser  # noqa: E402

XML_PATH = Path(__file__).with_name("debris.xml")
BINDINGS_PATH = Path(__file__).with_name("mavlink_debris.py")

#: System and component ids of the parties on the link.
FSW_SYSID = 1
FSW_COMPID = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER
GCS_SYSID = 255
GCS_COMPID = mavlink.MAV_COMP_ID_MISSIONPLANNER


def generate(output: Path, xml_path: Path = XML_PATH) -> None:
    """Run pymavlink's mavgen on `debris.xml` and write the Python (MAVLink 2) bindings to `output`.

    With mavgen's strict units (`--strict-units`): a field's or parameter's `units` must be one of the
    schema's list, so that every MAVLink tool reads them; other units go in the description.

    mavgen resolves `<include>` relative to the XML's folder, so the XML is generated from a temporary
    folder that also holds pymavlink's own copies of the included standard definitions.
    """
    from pymavlink.generator import mavgen, mavparse
    import pymavlink.dialects.v20 as std

    std_dir = Path(std.__file__).parent
    with tempfile.TemporaryDirectory() as tmp:
        tmpdir = Path(tmp)
        for name in ("common.xml", "standard.xml", "minimal.xml"):
            shutil.copy(std_dir / name, tmpdir / name)
        xml = tmpdir / "debris.xml"
        shutil.copy(xml_path, xml)
        out_base = tmpdir / "mavlink_debris"
        opts = mavgen.Opts(str(out_base), wire_protocol=mavparse.PROTOCOL_2_0, language="Python3",
                           validate=True, strict_units=True)
        try:
            ok = mavgen.mavgen(opts, [str(xml)])
        except SystemExit as e:  # mavgen exits on a schema error (e.g. a unit outside the strict list)
            raise RuntimeError(f"mavgen refused {xml_path}: {e}") from None
        if not ok:
            raise RuntimeError(f"mavgen failed on {xml_path}")
        shutil.copy(out_base.with_suffix(".py"), output)


def open_link(url: str, *, source_system: int, source_component: int, input: bool = False,
              **kwargs) -> mavutil.mavfile:
    """Open any pymavlink connection string (`udpout:HOST:PORT`, `udpin:...`, `tcp:...`, a serial
    device, a .tlog file) and bind it to the project dialect, MAVLink 2.

    `input` is mavutil's flag for udp: True listens (`udpin`), False sends (`udpout`); the URL's own
    prefix takes precedence.
    """
    conn = mavutil.mavlink_connection(url, source_system=source_system,
                                      source_component=source_component, input=input, **kwargs)
    conn.mav = mavlink.MAVLink(conn, srcSystem=source_system, srcComponent=source_component)
    conn.mav.robust_parsing = True
    return conn


def main(argv: list[str] | None = None) -> int:
    ap = ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--generate", action="store_true",
                    help=f"regenerate {BINDINGS_PATH.name} from {XML_PATH.name}")
    args = ap.parse_args(argv)
    if args.generate:
        generate(BINDINGS_PATH)
        print(f"wrote {BINDINGS_PATH}")
    return 0


if __name__ == "__main__":
    from fsw.startup import exit_with

    exit_with(main)
