"""The live web view in a real browser during a SITL run of two boxes: headless Chromium (the Debian package)
opens the station's page while two `hil.sitl` runs (system ids 1 and 2, the de-orbit scenario and the default
one, each signing with its own key) send to `ground.station`; for each box the page's
last plotted rows (``window.station.plotted``, read through the DevTools protocol with aiohttp's WebSocket
client) are the values of the very frames the station archived at those times, decoded independently from
the archive. A screenshot is kept in ``artifacts/station.png`` (git-ignored; the path is printed)."""
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


async def watch(port, url, boxes=("1", "2"), timeout_s=120.0):
    """Until the page has plotted, for every box, the field, the rate and its truth, the kit's energy: per box
    the last plotted rows and the rows it holds, the updates received, a screenshot (PNG bytes) of the first."""
    import base64

    async with ClientSession() as http:
        async with http.get(f"http://127.0.0.1:{port}/json/list") as r:
            page = next(t for t in await r.json() if t["type"] == "page")
        async with http.ws_connect(page["webSocketDebuggerUrl"], max_msg_size=0) as ws:
            cdp = Cdp(ws)
            await cdp.call("Page.enable")
            await cdp.call("Page.navigate", url=url)
            deadline = time.monotonic() + timeout_s
            need = {"1": ("field_uT", "rate_dps", "truth_rate_dps", "kit_energy_J"),  # box 1 flies the kit
                    "2": ("field_uT", "rate_dps", "truth_rate_dps")}
            plotted = {}
            while time.monotonic() < deadline:
                for box in boxes:  # each box's detail drawn in turn, as an operator clicks its row
                    got = await cdp.evaluate(
                        f"(() => {{ if (!window.station || !station.boxes['{box}']) return null;"
                        f" station.selected = '{box}'; render();"
                        f" return JSON.stringify(station.plotted['{box}']); }})()")
                    plotted[box] = json.loads(got or "{}")
                if all(all(k in plotted[b] for k in need[b]) and plotted[b]["field_uT"][0] > 8.0 for b in boxes):
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


def sitl(port, key_file, sysid, scenario):
    return subprocess.Popen([sys.executable, "-m", "hil.sitl", "--scenario", scenario, "--key", str(key_file),
                             "--system-id", str(sysid), "--sample-rate", "10", "--duration", "30", "--speed", "1",
                             "--link", f"udpout:127.0.0.1:{port}", "--quiet"], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def test_browser_shows_the_decoded_values_of_two_live_sitl_boxes(tmp_path):
    keys = {1: tmp_path / "box1.key", 2: tmp_path / "box2.key"}
    for path in keys.values():
        write_key(path, os.urandom(32))
    port = free_udp_port()
    archive = tmp_path / "archive.sqlite"
    station = subprocess.Popen([sys.executable, "-m", "ground.station", f"udpin:127.0.0.1:{port}",
                                "--box", f"1:{keys[1]}", "--box", f"2:{keys[2]}", "--web", "127.0.0.1:0",
                                "--archive", str(archive), "--quiet"],
                               cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    boxes, browser = [], None
    profile = Path(tempfile.mkdtemp(prefix="station-chromium-"))
    try:
        line = station.stdout.readline()
        assert line.startswith("web view: http://127.0.0.1:"), line + station.stderr.read()
        url = line.split()[-1]
        boxes = [sitl(port, keys[1], 1, "amds_deorbit"), sitl(port, keys[2], 2, "isoi")]
        browser = subprocess.Popen([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu",
                                    "--disable-background-networking", "--disable-component-update",
                                    "--disable-sync", "--no-first-run", "--hide-scrollbars",
                                    f"--user-data-dir={profile}", "--remote-debugging-port=0",
                                    "--window-size=1500,1250", "about:blank"],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        cdp_port = devtools_port(profile, browser)
        plotted, updates, n_rows, png = asyncio.run(watch(cdp_port, url))
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
        assert n_rows[str(sysid)]["field_uT"] >= 5, n_rows
        msgs = archived(archive, sysid)
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
    assert out.count("refused: none") == 2  # each box's frames verified with its own key
