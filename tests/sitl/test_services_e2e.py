"""The MAVLink services end to end: `hil.sitl` over UDP with a key made from a passphrase, and a plain
pymavlink connection signing with it the way MAVProxy does (`mavfile.setup_signing` with SHA-256 of
the passphrase), speaking to component 1 like a ground station that has not yet seen the box."""
import hashlib
import io
import threading
import time

import pytest

from fsw.telemetry import dialect
from fsw.telemetry.dialect import FSW_SYSID, mavlink
from ground import keys
from hil import sitl
from support import free_udp_port

pytestmark = [pytest.mark.sitl, pytest.mark.slow]  # ~15 s: the SITL build and its 6 s of wall time

PASSPHRASE = "tumbling-debris-2026"


def wait_for(conn, kind, deadline_s, pred=lambda m: True):
    while time.monotonic() < deadline_s:
        m = conn.recv_match(type=kind, blocking=True, timeout=0.2)
        if m is not None and pred(m):
            return m
    return None


def test_a_pymavlink_ground_station_signing_with_a_passphrase_key_sees_lists_and_sets(tmp_path):
    key_file = tmp_path / "mission.key"
    keys.key_from_passphrase(str(key_file), PASSPHRASE)
    port = free_udp_port()
    args = sitl.parse_args(["--speed", "4", "--quiet", "--duration", "24", "--key", str(key_file),
                            "--link", f"udpout:127.0.0.1:{port}"])
    out = {}
    th = threading.Thread(target=lambda: out.setdefault("run", sitl.run(args, out=io.StringIO())))
    th.start()
    conn = dialect.open_link(f"udpin:127.0.0.1:{port}", source_system=255, source_component=190, input=True)
    conn.setup_signing(hashlib.sha256(PASSPHRASE.encode("ascii")).digest(), sign_outgoing=True)
    try:
        deadline = time.monotonic() + 6.0
        hb = wait_for(conn, "HEARTBEAT", deadline)
        assert hb is not None and hb.autopilot == mavlink.MAV_AUTOPILOT_GENERIC  # a vehicle: "online"
        box = (hb.get_srcSystem(), 1)  # component 1: the system's autopilot
        conn.mav.param_request_list_send(*box)
        names = set()
        while len(names) < 4 and time.monotonic() < deadline:
            m = wait_for(conn, "PARAM_VALUE", deadline)
            if m is not None:
                names.add(m.param_id)
                count = m.param_count
        assert len(names) == count >= 4 and "TLM_SAMPLE_HZ" in names
        conn.mav.param_set_send(*box, b"TLM_SAMPLE_HZ", 0.5, mavlink.MAV_PARAM_TYPE_REAL32)
        v = wait_for(conn, "PARAM_VALUE", deadline, lambda m: m.param_id == "TLM_SAMPLE_HZ")
        assert v is not None and v.param_value == 0.5
        conn.mav.command_long_send(*box, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                                   mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0)
        av = wait_for(conn, "AUTOPILOT_VERSION", deadline)
        assert av is not None and av.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
        conn.mav.command_long_send(*box, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 0, 0)
        ack = wait_for(conn, "COMMAND_ACK", deadline, lambda m: m.command == mavlink.MAV_CMD_NAV_TAKEOFF)
        assert ack is not None and ack.result == mavlink.MAV_RESULT_UNSUPPORTED
    finally:
        conn.close()
        th.join()
    u = out["run"].fsw.uplink.counters
    assert u.params_set == 1 and u.bad_signature == 0 and u.unsigned == 0 and hb.get_srcSystem() == FSW_SYSID
