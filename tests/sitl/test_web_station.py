"""The live web view in a real browser during a SITL run of three boxes: headless Chromium (the Debian package)
opens the station's page while two `hil.sitl` runs (system ids 1 and 2, the de-orbit scenario and the default
one) and a third box in this process (system id 3, running the identification experiment), each
signing with its own key, send to `ground.station`; for each box the page's
last plotted rows (field, rate ± σ, truth, the truth's attitude, the kit's energy, the inertia estimate ± its
95 % band, the flown filter's attitude: ``window.station.plotted``, read through the DevTools protocol with
aiohttp's WebSocket client) are the values of the very frames the station archived at those times, decoded
independently from the archive. Boxes 1 and 2 fly the fixed-field filter (the orbit filters wait for the
host-magnetics calibration, about an orbit) and show no attitude of their own; box 3 starts with its host's
true iron as the calibration a restart would restore (`HostCalibration.restore`), so its flown filter hands
over to the Euler filter with the field along the orbit at its second sample and its ATTITUDE_QUATERNION
is plotted as yaw, pitch, roll. A screenshot is kept in ``artifacts/station.png`` (git-ignored; the path is printed)."""
import asyncio
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
from aiohttp import ClientSession

from fsw.telemetry.dialect import mavlink
from fsw.telemetry.signing import write_key
from ground.archive.store import frames, open_reader
from support import ROOT, free_udp_port

CHROMIUM = "/usr/bin/chromium"
ARTIFACTS = ROOT / "artifacts"

pytestmark = [pytest.mark.sitl, pytest.mark.slow,
              pytest.mark.skipif(not os.access(CHROMIUM, os.X_OK),
                                 reason=f"{CHROMIUM} is not installed (apt-get install chromium; .ci/run does)")]


class Cdp:
    """A page driven through Chrome's DevTools protocol."""

    def __init__(self, ws):
        self.ws, self.n = ws, 0

    async def call(self, method, **params):
        self.n += 1
        await self.ws.send_json({"id": self.n, "method": method, "params": params})
        while True:
            msg = json.loads((await self.ws.receive(timeout=60)).data)
            if msg.get("id") == self.n:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg["result"]

    async def evaluate(self, expression):
        r = await self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        return r["result"].get("value")


def devtools_port(profile: Path, proc, timeout_s=60.0) -> int:
    deadline = time.monotonic() + timeout_s
    f = profile / "DevToolsActivePort"
    while time.monotonic() < deadline:
        if f.exists() and f.read_text().strip():
            return int(f.read_text().split()[0])
        assert proc.poll() is None, "chromium exited"
        time.sleep(0.1)
    raise TimeoutError("chromium did not open its DevTools port")


#: what the page must have plotted of each box before it is read: box 1 flies the kit, box 3 identifies its
#: inertia with its host calibration restored, so it flies the orbit's filter and plots its own attitude
#: (boxes 1 and 2 fly the fixed-field filter, which has none: the orbit's filters wait for the host-magnetics
#: calibration, about an orbit).
NEED = {"1": ("field_uT", "rate_dps", "truth_rate_dps", "kit_energy_J", "truth_attitude_deg"),
        "2": ("field_uT", "rate_dps", "truth_rate_dps", "truth_attitude_deg"),
        "3": ("field_uT", "inertia_kgm2", "attitude_deg")}


async def watch(port, url, boxes=("1", "2", "3"), timeout_s=180.0, done=lambda: True):
    """Until the page has plotted, for every box, what `NEED` says (box time past 8 s) and `done()`: per box the
    last plotted rows and the rows it holds, the updates received, a screenshot (PNG bytes) of the first."""
    import base64

    async with ClientSession() as http:
        async with http.get(f"http://127.0.0.1:{port}/json/list") as r:
            page = next(t for t in await r.json() if t["type"] == "page")
        async with http.ws_connect(page["webSocketDebuggerUrl"], max_msg_size=0) as ws:
            cdp = Cdp(ws)
            await cdp.call("Page.enable")
            await cdp.call("Page.navigate", url=url)
            deadline = time.monotonic() + timeout_s
            plotted = {}
            while time.monotonic() < deadline:
                for box in boxes:  # each box's detail drawn in turn, as an operator clicks its row
                    got = await cdp.evaluate(
                        f"(() => {{ if (!window.station || !station.boxes['{box}']) return null;"
                        f" station.selected = '{box}'; render();"
                        f" return JSON.stringify(station.plotted['{box}']); }})()")
                    plotted[box] = json.loads(got or "{}")
                if done() and all(all(k in plotted[b] for k in NEED[b]) and plotted[b]["field_uT"][0] > 8.0
                                  for b in boxes):
                    break
                await asyncio.sleep(0.5)
            updates = await cdp.evaluate("(window.station||{}).updates||0")
            rows = json.loads(await cdp.evaluate(
                "JSON.stringify(Object.fromEntries(Object.entries(station.boxes).map(([id, b]) =>"
                " [id, Object.fromEntries(Object.entries(b.series).map(([k, s]) => [k, s.rows.length]))])))"))
            await cdp.evaluate(f"station.selected = '{boxes[0]}'; render()")
            shot = await cdp.call("Page.captureScreenshot", format="png")
            return plotted, updates, rows, base64.b64decode(shot["data"])


def archived(path, sysid=1):
    """Every archived message of `sysid`, decoded from the raw frames."""
    parser = mavlink.MAVLink(None)
    conn = open_reader(path)
    try:
        return [m for _, frame in frames(conn, sysid) for m in (parser.parse_buffer(frame) or [])]
    finally:
        conn.close()


def at(msgs, kind, t_s, **match):
    t_us = round(t_s * 1e6)
    hits = [m for m in msgs if m.get_type() == kind and m.time_usec == t_us
            and all(getattr(m, k) == v for k, v in match.items())]
    assert hits, f"no {kind} at {t_s} s in the archive"
    return hits[-1]


def euler_deg(q_wxyz):
    """Roll, pitch, yaw (deg) of a quaternion body → reference, by SciPy (Z-Y-X, intrinsic)."""
    from scipy.spatial.transform import Rotation

    w, x, y, z = q_wxyz
    yaw, pitch, roll = Rotation.from_quat([x, y, z, w]).as_euler("ZYX", degrees=True)
    return [roll, pitch, yaw]


def true_calibration(host, t_s=0.0) -> dict:
    """The simulated host's own iron (`hil.host_magnetics.HostMagnetics`: b_meas = S·b + h(t)) as a
    calibration snapshot (`fsw.estimation.magcal.MagCal.snapshot`'s format; B = (I + D)(B_meas − b)):
    b = h(`t_s`), I + D = S⁻¹ (symmetric: the scenarios' S is), no drift terms, converged."""
    import numpy as np

    from fsw.estimation import magcal as mc

    b_T = host.hard_iron_at_T(t_s)
    D = np.linalg.inv(host.soft_iron) - np.eye(3)
    D = (D + D.T) / 2.0
    theta = [*(b_T * mc.UT_PER_T), *(D[i, j] for i, j in mc.D_TERMS)]
    return {"theta_uT": [float(x) for x in theta], "b_T": [float(x) for x in b_T],
            "D": D.tolist(), "cov": None, "published_at_s": t_s, "drift_period_s": None, "state": mc.CONVERGED}


def identifying_box(port, key, sysid=3):
    """A third box, in this process: SITL of Aist-2D (1 Hz samples) whose identification experiment is started
    as the ground would (MAV_CMD_DEBRIS_IDENT_START, the tug), run faster than real time until it is done,
    its telemetry signed with `key` and sent to the station: running and final DEBRIS_INERTIA_ESTIMATE
    (the two other boxes never start the experiment). Its host-magnetics calibration is the host's true iron,
    restored before its first tick as after a restart (`true_calibration`): its flown filter hands over to
    the orbit's (Euler) filter and sends ATTITUDE_QUATERNION. Returns the thread and what it reached:
    the experiment's final state, the flown filter's name and hand-overs."""
    import dataclasses
    import threading
    from types import SimpleNamespace

    from fsw.ident import DONE
    from fsw.telemetry import dialect
    from hil import sitl as hil_sitl
    from support import flight_assumptions

    args = hil_sitl.parse_args(["--scenario", "aist2d_ident", "--rate", "10", "--speed", "0", "--quiet",
                                "--system-id", str(sysid)])
    args = dataclasses.replace(args, scenario=flight_assumptions("aist2d_ident"))
    state = {"final": None, "filter": None, "handovers": 0}

    def run():
        tx = dialect.open_link(f"udpout:127.0.0.1:{port}", source_system=sysid,
                               source_component=dialect.FSW_COMPID)
        try:
            box = hil_sitl.build(args, link=tx, key=key, ident_options={
                "work_per_tick": 200000, "update_every_s": 10.0, "tlm_period_s": 2.0})
            box.fsw.calibration.restore(true_calibration(box.sim.host), None, 0.0, restart=False)
            ident = box.fsw.apps["ident"]
            start = SimpleNamespace(command=mavlink.MAV_CMD_DEBRIS_IDENT_START, confirmation=0, target_system=sysid,
                                    target_component=1, param1=mavlink.DEBRIS_TORQUE_SOURCE_TUG, param2=20.0,
                                    param3=20.0, param4=20.0, param5=0.2, param6=0.15, param7=-0.1)
            k = 0
            while ident.state != DONE and k < 3000:
                t = k / args.run.rate_hz
                box.sim.advance_to(t)
                if k == 5:
                    box.fsw.commands.handle(start, t, authenticated=True)
                box.fsw.tick(t)
                if k % 10 == 0:
                    time.sleep(0.02)     # about 10 × real time: no burst for the station's socket
                k += 1
            for _ in range(30):          # its last telemetry after the final estimate
                k += 1
                box.sim.advance_to(k / args.run.rate_hz)
                box.fsw.tick(k / args.run.rate_hz)
            state["final"] = ident.state
            flown = box.fsw.estimators["kalman"]
            state["filter"], state["handovers"] = flown.name, flown.handovers
        finally:
            tx.close()

    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th, state


def sitl(port, key_file, sysid, scenario):
    return subprocess.Popen([sys.executable, "-m", "hil.sitl", "--scenario", scenario, "--key", str(key_file),
                             "--system-id", str(sysid), "--sample-rate", "10", "--duration", "30", "--speed", "1",
                             "--link", f"udpout:127.0.0.1:{port}", "--quiet"], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def test_browser_shows_the_decoded_values_of_three_live_sitl_boxes(tmp_path):
    keys = {1: tmp_path / "box1.key", 2: tmp_path / "box2.key", 3: tmp_path / "box3.key"}
    secrets = {sysid: os.urandom(32) for sysid in keys}
    for sysid, path in keys.items():
        write_key(path, secrets[sysid])
    port = free_udp_port()
    archive = tmp_path / "archive.sqlite"
    station = subprocess.Popen([sys.executable, "-m", "ground.station", f"udpin:127.0.0.1:{port}",
                                "--box", f"1:{keys[1]}", "--box", f"2:{keys[2]}", "--box", f"3:{keys[3]}",
                                "--web", "127.0.0.1:0",
                                "--archive", str(archive), "--quiet"],
                               cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    boxes, browser = [], None
    profile = Path(tempfile.mkdtemp(prefix="station-chromium-"))
    try:
        line = station.stdout.readline()
        assert line.startswith("web view: http://127.0.0.1:"), line + station.stderr.read()
        url = line.split()[-1]
        boxes = [sitl(port, keys[1], 1, "amds_deorbit"), sitl(port, keys[2], 2, "isoi")]
        ident_thread, ident = identifying_box(port, secrets[3])
        browser = subprocess.Popen([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu",
                                    "--disable-background-networking", "--disable-component-update",
                                    "--disable-sync", "--no-first-run", "--hide-scrollbars",
                                    f"--user-data-dir={profile}", "--remote-debugging-port=0",
                                    "--window-size=1500,1250", "about:blank"],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        cdp_port = devtools_port(profile, browser)
        ended = []

        def settled():  # box 3's experiment done, and two seconds for its last frames to be drawn
            if not ident_thread.is_alive() and not ended:
                ended.append(time.monotonic())
            return bool(ended) and time.monotonic() > ended[0] + 2.0

        plotted, updates, n_rows, png = asyncio.run(watch(cdp_port, url, done=settled))
    finally:
        for p in (browser, *boxes):
            if p is not None and p.poll() is None:
                p.send_signal(signal.SIGTERM)
                p.wait(timeout=60)
        station.send_signal(signal.SIGTERM)
        out, err = station.communicate(timeout=60)
        shutil.rmtree(profile, ignore_errors=True)
    ARTIFACTS.mkdir(exist_ok=True)
    shot = ARTIFACTS / "station.png"
    shot.write_bytes(png)
    print(f"screenshot of the station's page: {shot}")
    assert station.returncode == 0, err
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000
    assert updates >= 8, updates

    for sysid in (1, 2):
        box = plotted[str(sysid)]
        msgs = archived(archive, sysid)
        assert n_rows[str(sysid)]["field_uT"] >= 5, n_rows
        assert "attitude_deg" not in box                   # the fixed-field filter flies: no attitude of its own
        t, *att = box["truth_attitude_deg"]
        assert att == pytest.approx(euler_deg(at(msgs, "DEBRIS_SIM_STATE", t).q), abs=1e-3)
        t, *b_uT = box["field_uT"]
        assert t > 8.0
        sample = at(msgs, "DEBRIS_MAG_SAMPLE", t)
        assert b_uT == pytest.approx([x * 100 for x in sample.mag], abs=1e-3)  # gauss → µT
        t, *w = box["rate_dps"]
        est = at(msgs, "DEBRIS_RATE_ESTIMATE", t, method=mavlink.DEBRIS_RATE_METHOD_KALMAN)
        assert w == pytest.approx([math.degrees(x) for x in (est.wx, est.wy, est.wz, est.sx, est.sy, est.sz)],
                                  abs=1e-3)
        t, *w = box["truth_rate_dps"]
        truth = at(msgs, "DEBRIS_SIM_STATE", t)
        assert w == pytest.approx([math.degrees(x) for x in (truth.wx, truth.wy, truth.wz)], abs=1e-3)
        if sysid == 1:
            t, *energy = box["kit_energy_J"]
            assert energy == pytest.approx(list(at(msgs, "DEBRIS_DEORBIT_STATUS", t).energy), abs=1e-3)
        else:
            assert "kit_energy_J" not in box  # the default scenario has no kit: nothing of box 1's shown for it
        assert f"box {sysid}: " in out
    assert out.count("refused: none") == 3  # each box's frames verified with its own key

    # box 3's identification: the estimate converging with its 95 % band is the archived one's
    assert ident["final"] == mavlink.DEBRIS_IDENT_STATE_DONE
    msgs = archived(archive, 3)
    estimates = [m for m in msgs if m.get_type() == "DEBRIS_INERTIA_ESTIMATE" and m.samples]
    assert len(estimates) >= 3 and estimates[-1].state == mavlink.DEBRIS_IDENT_STATE_DONE
    t, *inertia = plotted["3"]["inertia_kgm2"]
    est = at(msgs, "DEBRIS_INERTIA_ESTIMATE", t)
    assert inertia == pytest.approx([*est.inertia[:3], *est.ci95[:3]], abs=1e-3)   # Ixx Iyy Izz and their 95 %
    assert est.time_usec == max(m.time_usec for m in estimates)                      # the newest: the final one
    assert n_rows["3"]["inertia_kgm2"] >= 3

    # box 3's own attitude: the flown filter handed over once to the Euler filter, which flew to the end;
    # the plotted yaw/pitch/roll are the archived ATTITUDE_QUATERNION's (body → ECI) at the plotted time
    assert (ident["filter"], ident["handovers"]) == ("euler", 1), ident
    sigmas = [m for m in msgs if m.get_type() == "DEBRIS_ATTITUDE_SIGMA"]
    assert sigmas[-1].filter == mavlink.DEBRIS_RATE_FILTER_EULER and sigmas[-1].handovers == 1
    t, *att = plotted["3"]["attitude_deg"]
    t_ms = round(t * 1e3)
    quats = [m for m in msgs if m.get_type() == "ATTITUDE_QUATERNION" and m.time_boot_ms == t_ms]
    assert quats, f"no ATTITUDE_QUATERNION at {t} s in the archive"
    q = quats[-1]
    assert att == pytest.approx(euler_deg((q.q1, q.q2, q.q3, q.q4)), abs=1e-3)   # degrees
    assert n_rows["3"]["attitude_deg"] >= 3
