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


#: the project's range (docs/telemetry.md, "Message and command ids")
PRIVATE = range(54000, 54100)


def _registered_dialects():
    """Every dialect XML pymavlink ships (MAVLink's registered dialects: mavlink/mavlink's
    message_definitions), with the message ids and MAV_CMD values each defines."""
    from pathlib import Path

    from lxml import etree
    import pymavlink.dialects.v20 as v20

    for path in sorted(Path(v20.__file__).parent.glob("*.xml")):
        tree = etree.parse(str(path))
        msgs = {int(m.get("id")) for m in tree.iter("message")}
        cmds = {int(e.get("value")): e for en in tree.iter("enum") if en.get("name") == "MAV_CMD"
                for e in en.iter("entry")}
        yield path.name, msgs, cmds


def test_the_dialects_ids_are_in_a_range_no_registered_dialect_uses():
    m = dialect.mavlink
    ours = {i for i, cls in m.mavlink_map.items() if cls.msgname.startswith("DEBRIS_")}
    our_cmds = {v for v, e in m.enums["MAV_CMD"].items() if e.name.startswith("MAV_CMD_DEBRIS_")}
    assert ours and our_cmds and ours <= set(PRIVATE) and our_cmds <= set(PRIVATE)
    seen = []
    for name, msgs, cmds in _registered_dialects():
        assert not msgs & set(PRIVATE) and not cmds.keys() & set(PRIVATE), name
        seen.append(name)
    assert {"common.xml", "ardupilotmega.xml", "ASLUAV.xml", "storm32.xml", "AVSSUAS.xml", "uAvionix.xml",
            "cubepilot.xml", "csAirLink.xml", "icarous.xml", "development.xml"} <= set(seen)


def test_protocol_version_is_in_no_included_dialect_so_the_box_refuses_it():
    """PROTOCOL_VERSION (300) is not in the common.xml the dialect includes (deprecated 2025-11 and
    removed; MAV_CMD_REQUEST_PROTOCOL_VERSION deprecated, replaced by MAV_CMD_REQUEST_MESSAGE): the box
    cannot send it and answers its requests DENIED / UNSUPPORTED (tests/fsw/test_services.py). If a
    pymavlink brings it back, the box should answer it: this test says so."""
    m = dialect.mavlink
    assert 300 not in m.mavlink_map, "PROTOCOL_VERSION is defined again: answer MAV_CMD_REQUEST_MESSAGE(300)"
    dialects = {name: (msgs, cmds) for name, msgs, cmds in _registered_dialects()}
    assert all(300 not in msgs for msgs, _ in dialects.values())
    deprecated = dialects["common.xml"][1][m.MAV_CMD_REQUEST_PROTOCOL_VERSION].find("deprecated")
    assert deprecated is not None and deprecated.get("replaced_by") == "MAV_CMD_REQUEST_MESSAGE"
