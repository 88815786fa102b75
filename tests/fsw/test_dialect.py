"""The committed MAVLink bindings are what mavgen makes of the dialect XML, and speak MAVLink 2."""
import difflib

import pytest

from fsw.telemetry import dialect


def test_bindings_in_sync_with_xml(tmp_path):
    out = tmp_path / "mavlink_debris.py"
    dialect.generate(out)
    fresh = out.read_text().splitlines()
    committed = dialect.BINDINGS_PATH.read_text().splitlines()
    if fresh != committed:
        diff = "\n".join(list(difflib.unified_diff(committed, fresh, "committed", "generated", lineterm=""))[:40])
        raise AssertionError(f"{dialect.BINDINGS_PATH.name} is out of date: run `make dialect`\n{diff}")


def test_dialect_messages_in_private_range_and_mavlink2():
    m = dialect.mavlink
    assert m.WIRE_PROTOCOL_VERSION == "2.0"
    ids = [m.MAVLINK_MSG_ID_DEBRIS_RATE_ESTIMATE, m.MAVLINK_MSG_ID_DEBRIS_SIM_STATE,
           m.MAVLINK_MSG_ID_DEBRIS_LOOP_STATUS, m.MAVLINK_MSG_ID_DEBRIS_MAG_STATUS]
    assert all(54000 <= i < 54100 for i in ids)
    frame = m.MAVLink_debris_rate_estimate_message(1, 0.1, 0.2, 0.3, 0.01, 0.02, 0.03, 1, 1).pack(
        m.MAVLink(None, srcSystem=1, srcComponent=191))
    assert frame[0] == 0xFD   # MAVLink 2 start byte
    back = m.MAVLink(None).parse_char(frame)
    assert back.get_type() == "DEBRIS_RATE_ESTIMATE" and abs(back.wy - 0.2) < 1e-7


def test_dialect_passes_mavgen_strict_units(tmp_path):
    """The generation runs mavgen with strict units (every unit from the schema's list); a unit outside
    it (the N.m the dialect used to carry) is refused, so the check is real."""
    dialect.generate(tmp_path / "strict.py")  # raises on a unit outside the list
    bad = tmp_path / "debris.xml"
    text = dialect.XML_PATH.read_text()
    bad.write_text(text.replace('units="rad/s"', 'units="N.m"', 1))
    assert 'units="N.m"' in bad.read_text()
    with pytest.raises(RuntimeError, match="N.m"):
        dialect.generate(tmp_path / "bad.py", bad)
