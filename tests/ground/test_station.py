"""The station's web view: a real aiohttp server on port 0 (page, static files, WebSocket snapshot and updates),
fleets (each box's frames checked with its own key; a frame signed with another box's key refused and
counted), no secret in anything served, bounded rings; the command line against UDP frames from two boxes."""
import asyncio
import base64
import json
import math
import os
import signal
import sqlite3
import subprocess
import sys
import time

import pytest
from aiohttp import ClientSession, web

from fsw.telemetry.dialect import mavlink
from fsw.telemetry.signing import write_key
from ground.keys import passphrase_key
from ground.web import boxview
from ground.web.fleet import Fleet
from ground.web.server import WebView
from ground.web.synthetic import SyntheticBox
from support import ROOT, exit_status, free_udp_port

T0 = 1.8e9  # a Unix time for the signatures


def feed(fleet, box, t_s_list):
    parser = mavlink.MAVLink(None)
    for t in t_s_list:
        for frame in box.frames(t, T0 + t):
            for msg in parser.parse_buffer(frame) or []:
                fleet.handle(msg, T0 + t)


class Served:
    """A WebView on a real server at 127.0.0.1:0, with an HTTP session."""

    def __init__(self, fleet, publish_period_s=3600.0):
        self.view = WebView(fleet, clock=lambda: T0, publish_period_s=publish_period_s)

    async def __aenter__(self):
        self.runner = web.AppRunner(self.view.app())
        await self.runner.setup()
        site = web.TCPSite(self.runner, "127.0.0.1", 0)
        await site.start()
        self.url = f"http://127.0.0.1:{self.runner.addresses[0][1]}"
        self.session = ClientSession()
        return self

    async def __aexit__(self, *exc):
        await self.session.close()
        await self.runner.cleanup()


def test_page_and_its_files_are_served_from_the_package_read_only():
    async def go():
        async with Served(Fleet()) as s:
            async with s.session.get(s.url + "/") as r:
                assert r.status == 200 and r.content_type == "text/html"
                page = await r.text()
            assert "<canvas" in page and "/static/station.js" in page
            texts = [page]
            for name, kind in (("station.js", "text/javascript"), ("station.css", "text/css")):
                async with s.session.get(f"{s.url}/static/{name}") as r:
                    assert r.status == 200 and r.content_type == kind
                    assert "default-src 'self'" in r.headers["Content-Security-Policy"]
                    texts.append(await r.text())
            for bad in ("/static/..%2Fserver.py", "/static/boxview.py", "/static/.hidden.js", "/nothing"):
                async with s.session.get(s.url + bad) as r:
                    assert r.status == 404, bad
            for method in ("POST", "PUT", "DELETE"):  # read-only: no endpoint takes anything
                async with s.session.request(method, s.url + "/") as r:
                    assert r.status == 405
            return texts

    texts = asyncio.run(go())
    for text in texts:  # nothing fetched from elsewhere at run time
        assert "http://" not in text and "https://" not in text and "//cdn" not in text


def test_websocket_sends_a_snapshot_then_updates_with_the_decoded_values():
    key = os.urandom(32)
    fleet = Fleet({1: key})
    box = SyntheticBox(1, key)
    feed(fleet, box, [i * 0.05 for i in range(40)])

    async def go():
        async with Served(fleet) as s:
            s.view.publish()  # the rows so far are published: the snapshot holds them
            async with s.session.ws_connect(s.url + "/ws") as ws:
                snap = json.loads((await ws.receive()).data)
                feed(fleet, box, [2.0 + i * 0.05 for i in range(21)])
                s.view.publish()
                upd = json.loads((await ws.receive()).data)
                s.view.publish()  # nothing new: the box is left out
                idle = json.loads((await ws.receive()).data)
            return snap, upd, idle

    snap, upd, idle = asyncio.run(go())
    assert snap["type"] == "snapshot" and upd["type"] == "update" and upd["seq"] == snap["seq"] + 1
    rows = snap["boxes"]["1"]["series"]["field_uT"]["rows"]
    assert rows[-1][0] == pytest.approx(1.95)
    assert rows[-1][1:] == pytest.approx(box.field_at(1.95), abs=1e-3)
    new = upd["boxes"]["1"]["rows"]["field_uT"]
    t_new = [r[0] for r in new]  # 21 rows over 1 s of box time: 10 a second, the newest always
    assert t_new[0] >= 1.95 + boxview.MIN_DT_S - 1e-9 and 9 <= len(new) <= 11
    assert all(b - a >= boxview.MIN_DT_S - 1e-9 for a, b in zip(t_new[:-2], t_new[1:-1]))
    assert new[-1][0] == pytest.approx(3.0)  # the newest is always published
    assert new[-1][1:] == pytest.approx(box.field_at(3.0), abs=1e-3)
    rate = upd["boxes"]["1"]["rows"]["rate_dps"][-1]
    assert rate[1:4] == pytest.approx((6.0, -5.0, 6.5), abs=1e-3)
    assert rate[4:] == pytest.approx([math.degrees(s) for s in (0.01, 0.02, 0.03)], abs=1e-3)
    assert upd["boxes"]["1"]["rows"]["truth_rate_dps"][-1][1:] == pytest.approx((6.0, -5.0, 6.5), abs=1e-3)
    state = upd["boxes"]["1"]["state"]
    assert state["verified"] and state["link"]["lost"] == 0 and state["rejected"] == {}
    assert state["filter"] == "euler"
    assert idle["seq"] == upd["seq"] + 1 and idle["boxes"] == {}


def test_two_boxes_each_decoded_with_its_own_key_and_a_wrongly_signed_frame_refused_and_counted():
    k1, k2 = os.urandom(32), os.urandom(32)
    fleet = Fleet({1: k1, 2: k2})
    feed(fleet, SyntheticBox(1, k1, rate_dps=(1.0, 2.0, 3.0)), [i * 0.1 for i in range(30)])
    feed(fleet, SyntheticBox(2, k2, rate_dps=(-4.0, 5.0, -6.0)), [i * 0.1 for i in range(30)])
    # box 2's system id, box 1's key (and values box 2 never sends): refused by box 2, not plotted
    forger = SyntheticBox(2, k1, rate_dps=(40.0, 40.0, 40.0))
    feed(fleet, forger, [3.05])
    sent_by_forger = 3 + 4  # one sample's frames and the once-a-second ones
    feed(fleet, SyntheticBox(3, k1), [0.0])  # an unlisted system id: counted, not shown
    fleet.update(T0)
    snap = fleet.snapshot(T0)
    b1, b2 = snap["boxes"]["1"], snap["boxes"]["2"]
    assert set(snap["boxes"]) == {"1", "2"}
    assert b1["state"]["rejected"] == {} and b1["state"]["authentic"] == b1["state"]["frames"]
    assert b2["state"]["rejected"] == {"bad_signature": sent_by_forger}
    assert b2["state"]["frames"] - b2["state"]["authentic"] == sent_by_forger
    assert b1["series"]["rate_dps"]["rows"][-1][1:4] == pytest.approx((1.0, 2.0, 3.0), abs=1e-3)
    assert all(r[1:4] == pytest.approx((-4.0, 5.0, -6.0), abs=1e-3) for r in b2["series"]["rate_dps"]["rows"])
    assert snap["station"]["other_frames"] == sent_by_forger and snap["station"]["other_systems"] == 1


def test_one_key_for_every_box_and_no_key_means_not_verified():
    key = os.urandom(32)
    fleet = Fleet(default_key=key)
    feed(fleet, SyntheticBox(7, key), [0.0, 0.1])
    feed(fleet, SyntheticBox(8, os.urandom(32)), [0.0])  # nothing authentic: no view made
    feed(fleet, SyntheticBox(9, None), [0.0])  # unsigned
    assert sorted(fleet.boxes) == [7] and sum(fleet.other_frames.values()) == 14
    open_fleet = Fleet()
    feed(open_fleet, SyntheticBox(9, None), [0.0])
    snap = open_fleet.snapshot(T0)
    assert not snap["station"]["verified"] and not snap["boxes"]["9"]["state"]["verified"]


def test_nothing_served_holds_a_key_or_passphrase(tmp_path):
    passphrase = "correct-horse-battery-staple"
    keys = {1: passphrase_key(passphrase), 2: os.urandom(32)}
    key_file = tmp_path / "box2-secret.key"
    write_key(key_file, keys[2])
    fleet = Fleet(keys)
    for sysid, key in keys.items():
        feed(fleet, SyntheticBox(sysid, key), [i * 0.1 for i in range(20)])
        box = SyntheticBox(sysid, key)

    async def go():
        async with Served(fleet) as s:
            texts = []
            async with s.session.ws_connect(s.url + "/ws") as ws:
                texts.append((await ws.receive()).data)
                feed(fleet, box, [5.0])
                s.view.publish()
                texts.append((await ws.receive()).data)
            for path in ("/", "/static/station.js", "/static/station.css", "/api/snapshot"):
                async with s.session.get(s.url + path) as r:
                    texts.append(await r.text())
            return texts

    texts = asyncio.run(go())
    assert json.loads(texts[0])["boxes"]["1"]["state"]["authentic"] > 0
    secrets = [passphrase, key_file.name, str(key_file)]
    for key in keys.values():
        secrets += [key.hex(), key.hex().upper(), base64.b64encode(key).decode(),
                    base64.urlsafe_b64encode(key).decode().rstrip("="), key.decode("latin-1"),
                    json.dumps(list(key))[1:-1], json.dumps(list(key)).replace(" ", "")[1:-1]]
    for text in texts:
        for secret in secrets:
            assert secret not in text


def test_rings_are_bounded_and_keep_the_newest_at_any_rate():
    s = boxview.Series(("v",), window_s=60.0)
    for k in range(2000):  # 2000 publications of 250 rows each: a kHz box for 500 s
        for i in range(250):
            s.add((k * 0.25 + i * 0.001, float(k * 250 + i)))
        out = s.flush()
        assert out[-1][1] == k * 250 + 249 and len(s.pending) == 0  # the newest always published
        assert 2 <= len(out) <= 4  # 0.25 s of box time at 10 rows a second
    t = [r[0] for r in s.ring]
    assert t[-1] - t[0] <= 60.0 and len(t) == pytest.approx(60.0 / 0.25 * 3, rel=0.05)
    assert len(s.ring) <= s.ring.maxlen
    s.add((0.0, 1.0))  # older than the newest: counted, not plotted
    assert s.late == 1 and s.flush() == []
    for i in range(3 * boxview.MAX_PENDING):  # a publication late: the waiting rows are thinned
        s.add((1000.0 + i * 0.001, float(i)))
    assert len(s.pending) <= boxview.MAX_PENDING and s.pending[-1][1] == 3 * boxview.MAX_PENDING - 1
    late = s.flush()  # and the rows of those 12 s are published 10 a second, as if on time
    assert len(late) == pytest.approx(3 * boxview.MAX_PENDING * 0.001 / boxview.MIN_DT_S, rel=0.05)


def test_a_new_run_of_the_flight_software_clears_the_plots():
    fleet = Fleet()
    feed(fleet, SyntheticBox(1, None, run_id=1), [10.0, 10.1])
    fleet.update(T0)
    feed(fleet, SyntheticBox(1, None, run_id=2), [0.0])
    u = fleet.update(T0)["boxes"]["1"]
    assert "field_uT" in u["reset"] and u["rows"]["field_uT"][-1][0] == 0.0
    assert "new run" in u["events"][-1]["text"]


def test_statustext_and_command_ack_reach_the_event_log():
    fleet = Fleet()
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
    parser = mavlink.MAVLink(None)
    frames = [mavlink.MAVLink_statustext_message(mavlink.MAV_SEVERITY_WARNING, b"sample rate lowered to 500 Hz"),
              mavlink.MAVLink_command_ack_message(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAV_RESULT_ACCEPTED)]
    for m in frames:
        for msg in parser.parse_buffer(m.pack(mav)):
            fleet.handle(msg, T0)
    events = fleet.update(T0)["boxes"]["1"]["events"]
    assert [(e["severity"], e["text"]) for e in events] == [
        ("warning", "sample rate lowered to 500 Hz"), ("ack", "REQUEST_MESSAGE: ACCEPTED")]


def _get_json(url, timeout_s=30.0):
    import urllib.request

    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with urllib.request.urlopen(url, timeout=5) as r:
                return json.loads(r.read())
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def start_station(args, cwd=ROOT):
    """`python -m ground.station ARGS` in the background; returns the process and the web view's URL."""
    proc = subprocess.Popen([sys.executable, "-m", "ground.station", *args], cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    assert line.startswith("web view: http://"), (line, proc.stderr.read() if proc.poll() is not None else "")
    return proc, line.split()[-1]


def test_command_line_two_boxes_over_udp_archived_and_shown(tmp_path):
    import socket

    k1, k2 = os.urandom(32), os.urandom(32)
    write_key(tmp_path / "1.key", k1)
    write_key(tmp_path / "2.key", k2)
    port = free_udp_port()
    archive = tmp_path / "a.sqlite"
    proc, url = start_station([f"udpin:127.0.0.1:{port}", "--box", f"1:{tmp_path / '1.key'}", "--box",
                               f"2:{tmp_path / '2.key'}", "--web", "127.0.0.1:0", "--archive", str(archive),
                               "--quiet"])
    try:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        boxes = [SyntheticBox(1, k1), SyntheticBox(2, k2), SyntheticBox(2, k1)]
        now = time.time()
        sent = {1: 0, 2: 0}
        for i in range(40):
            for j, b in enumerate(boxes):
                if j == 2 and i != 20:
                    continue
                for frame in b.frames(i * 0.1, now + i * 0.1):
                    sock.sendto(frame, ("127.0.0.1", port))
                    sent[b.sysid] += 1
            time.sleep(0.005)
        deadline = time.monotonic() + 30
        while True:
            snap = _get_json(url + "api/snapshot")
            got = {int(k): b["state"]["frames"] for k, b in snap["boxes"].items()}
            rows = snap["boxes"].get("1", {}).get("series", {}).get("field_uT", {}).get("rows") or [[0]]
            if (got == sent and rows[-1][0] == pytest.approx(3.9)) or time.monotonic() > deadline:
                break
            time.sleep(0.3)
        assert got == sent
        assert snap["boxes"]["2"]["state"]["rejected"] == {"bad_signature": 7}
        assert snap["boxes"]["1"]["state"]["rejected"] == {}
        assert rows[-1][1:] == pytest.approx(boxes[0].field_at(3.9), abs=1e-3)
    finally:
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert "box 2: " in out and "bad_signature 7" in out
    with sqlite3.connect(archive) as db:
        by_box = dict(db.execute("SELECT sysid, COUNT(*) FROM frames GROUP BY sysid"))
    assert by_box == sent


@pytest.mark.parametrize("args, message, status", [
    (["--box", "0:x.key"], "SYSID 1..255", 2),
    (["--box", "1"], "SYSID:KEYFILE", 2),
    (["--web", "8080"], "HOST:PORT", 2),
    (["--key", "no-such.key"], "no-such.key: cannot read key file", 1),
])
def test_bad_options_are_one_line_without_traceback(capsys, args, message, status):
    from ground.station import main

    assert exit_status(main, ["udpin:127.0.0.1:1", "--no-archive", *args]) == status
    err = capsys.readouterr().err
    assert message in err.strip().splitlines()[-1] and "Traceback" not in err  # argparse's usage, then one line


def test_inertia_kit_sail_attitude_and_backlog_are_plotted_in_display_units():
    fleet = Fleet()
    mav = mavlink.MAVLink(None, srcSystem=4, srcComponent=191)
    parser = mavlink.MAVLink(None)
    half = math.radians(30.0) / 2  # 30° about z
    nan = float("nan")
    msgs = [
        mavlink.MAVLink_debris_inertia_estimate_message(2_000_000, 120, [280.0, 270.0, 285.0, 0.1, 0.2, 0.3],
                                                        [3.0, 2.5, 4.0, 0.1, 0.1, 0.1], [4.0] * 6,
                                                        mavlink.DEBRIS_IDENT_STATE_TORQUE, 7),
        mavlink.MAVLink_debris_deorbit_status_message(2_000_000, [10, -20], [400, 200], [1.5, 0.25], [2, 1],
                                                      [1, 0], 0, [mavlink.DEBRIS_CAPSULE_STATE_OPEN,
                                                                  mavlink.DEBRIS_CAPSULE_STATE_CLOSED],
                                                      [mavlink.DEBRIS_MAGNET_STATE_IDLE,
                                                       mavlink.DEBRIS_MAGNET_STATE_TURNING], [1, -1], [0, 2],
                                                      mavlink.DEBRIS_CONTROLLER_STATE_RUNNING),
        mavlink.MAVLink_debris_deorbit_attitude_message(2_000_000, math.radians(12.0), math.radians(-3.0), 0.0,
                                                        [0.0] * 3, [0.01, 0.01], 0.001, 1, 4, 0),
        mavlink.MAVLink_debris_deorbit_attitude_message(2_100_000, nan, nan, nan, [nan] * 3, [nan, nan], nan, 0, 0, 0),
        mavlink.MAVLink_attitude_quaternion_message(2000, math.cos(half), 0.0, 0.0, math.sin(half), 0.0, 0.0, 0.0,
                                                    [0.0] * 4),
        mavlink.MAVLink_debris_link_status_message(2_000_000, 3, 1, 2, 0, 1, 57, 12, 0, 0),
    ]
    for m in msgs:
        for msg in parser.parse_buffer(m.pack(mav)):
            fleet.handle(msg, T0)
    u = fleet.update(T0)["boxes"]["4"]
    assert u["rows"]["inertia_kgm2"] == [[2.0, 280.0, 270.0, 285.0, 3.0, 2.5, 4.0]]
    assert u["state"]["inertia"]["state"] == "torque" and u["state"]["inertia"]["samples"] == 120
    assert u["rows"]["kit_energy_J"] == [[2.0, 1.5, 0.25]] and u["rows"]["kit_steps"] == [[2.0, 400.0, 200.0]]
    kit = u["state"]["kit"]
    assert kit["capsules"] == ["open", "closed"] and kit["magnets"] == ["idle", "turning"]
    assert kit["pulses"] == [400, 200] and kit["faults"] == [0, 2] and kit["controller"] == "running"
    assert u["rows"]["sail_deg"] == [[2.0, 12.0, -3.0]]  # the NaN one (no attitude) is not plotted
    assert u["state"]["sail"]["yaw_deg"] is None
    assert u["rows"]["attitude_deg"] == [[2.0, 0.0, 0.0, pytest.approx(30.0, abs=1e-3)]]
    assert u["rows"]["backlog_frames"] == [[2.0, 57.0, 12.0, 0.0]]
    assert u["state"]["box_link"]["uplink_rejected"] == 4 and u["state"]["box_link"]["link_up"] == 0
    json.dumps(fleet.snapshot(T0), allow_nan=False)  # valid JSON: no NaN anywhere


def test_loss_is_counted_from_sequence_numbers_per_box():
    key = os.urandom(32)
    fleet = Fleet({1: key})
    box = SyntheticBox(1, key)
    parser = mavlink.MAVLink(None)
    sent = 0
    for i in range(20):
        for j, frame in enumerate(box.frames(i * 0.1, T0 + i * 0.1)):
            sent += 1
            if i % 5 == 2 and j == 0:  # every fifth sample's DEBRIS_MAG_SAMPLE lost on the way
                continue
            for msg in parser.parse_buffer(frame) or []:
                fleet.handle(msg, T0 + i * 0.1)
    link = fleet.update(T0)["boxes"]["1"]["state"]["link"]
    assert link["lost"] == 4 and link["received"] == sent - 4
    assert link["loss_fraction"] == pytest.approx(4 / sent, abs=1e-5)


def test_a_fleet_in_sitl_one_run_per_system_id():
    from hil import sitl

    assert sitl.parse_args(["--system-id", "7"]).run.system_id == 7
    assert sitl.parse_args([]).run.system_id == 1


def test_the_methods_offered_are_the_ones_the_box_sends():
    from fsw.flight import METHODS

    assert set(boxview.ONBOARD_METHODS) == set(METHODS)


def test_a_frame_the_view_fails_on_is_archived_counted_and_the_station_goes_on(tmp_path, monkeypatch):
    import socket

    from ground.station import Ingest

    def broken(self, msg, now_s):
        raise KeyError("a fault of the view")

    monkeypatch.setitem(boxview.BoxView._HANDLERS, "STATUSTEXT", broken)
    fleet = Fleet()
    port = free_udp_port()
    said = []
    ingest = Ingest(fleet, [f"udpin:127.0.0.1:{port}"], archive=tmp_path / "a.sqlite", say=said.append)
    ingest.start()
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
    box = SyntheticBox(1, None)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.sendto(mavlink.MAVLink_statustext_message(mavlink.MAV_SEVERITY_INFO, b"hello").pack(mav),
                    ("127.0.0.1", port))
        frames = box.frames(1.0, T0)
        for frame in frames:
            sock.sendto(frame, ("127.0.0.1", port))
        deadline = time.monotonic() + 20
        while fleet.frames < 1 + len(frames) and time.monotonic() < deadline:
            time.sleep(0.05)
    ingest.stop()
    assert fleet.failures == {"STATUSTEXT: KeyError": 1} and len(said) == 1 and "goes on" in said[0]
    assert fleet.update(T0)["boxes"]["1"]["rows"]["field_uT"][-1][0] == 1.0
    with sqlite3.connect(tmp_path / "a.sqlite") as db:
        assert db.execute("SELECT COUNT(*) FROM frames").fetchone()[0] == 1 + len(frames)
