"""The ground station under a fleet's load: update rate and latency of the web view, the station's CPU and memory.

    python -m bench.station_load [--boxes N] [--sample-hz HZ ...] [--seconds S] [--json FILE]

For each ``--sample-hz`` (samples a second per box), ``python -m ground.station`` runs as an operator starts it
(one UDP link, ``--box SYSID:KEYFILE`` for each of the N boxes, the archive on) and this process sends, from a
thread, each box's synthetic telemetry signed with its own key (`ground.web.synthetic`: per sample
DEBRIS_MAG_SAMPLE, DEBRIS_RATE_ESTIMATE and DEBRIS_SIM_STATE, plus four frames once a second). A box's time
is the Unix time the sample was sent, so a WebSocket client on the view (aiohttp) reads the latency of every
update directly: the time it arrives minus the newest field row it carries for that box (send → UDP → ingest
→ archive and fleet → publication → WebSocket → client). Reported per rate: frames sent a second, updates a
second per box (the lowest of the boxes), latency p50 / p99 / max, the station's CPU (user + system, as a
share of one core) and its resident memory at the end, frames archived.

The box's highest telemetry rate by default is 20 samples/s (``--max-sample-tlm-hz``): five frames a sample
with the three estimators and SITL's truth, about 100 frames/s a box. The figures depend on the machine and
what else runs on it; the JSON has the load average. The targets (issue 18): ≥ 2 updates/s per box and
≤ 1 s latency for 10 boxes at once.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from aiohttp import ClientSession

from fsw.argtypes import finite_float, int_range
from fsw.telemetry.signing import write_key
from ground.web.synthetic import SyntheticBox

FIRST_SYSID = 1


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _rss_MB(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _free_udp_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _send(boxes: list[SyntheticBox], port: int, sample_hz: float, stop: threading.Event, sent: list) -> None:
    import socket

    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    period = 1.0 / sample_hz
    next_s = time.time()
    while not stop.is_set():
        now = time.time()
        if now < next_s:
            time.sleep(min(next_s - now, 0.05))
            continue
        next_s += period
        if next_s < now - 1.0:  # fell behind by more than a second: the schedule restarts (counted in sent)
            next_s = now
        for box in boxes:
            for frame in box.frames(now, now):
                sock.sendto(frame, ("127.0.0.1", port))
                sent[0] += 1
    sock.close()


async def _watch(url: str, seconds: float, warmup_s: float) -> dict:
    lat: list[float] = []
    oldest: list[float] = []
    updates: dict[str, int] = {}
    async with ClientSession() as http:
        async with http.ws_connect(url.replace("http://", "ws://") + "ws", max_msg_size=0) as ws:
            start = time.time()
            while time.time() - start < warmup_s + seconds:
                msg = await ws.receive(timeout=10)
                now = time.time()
                data = json.loads(msg.data)
                if data["type"] != "update" or now - start < warmup_s:
                    continue
                for sysid, u in data["boxes"].items():
                    rows = u["rows"].get("field_uT")
                    if rows:
                        updates[sysid] = updates.get(sysid, 0) + 1
                        lat.append(now - rows[-1][0])
                        oldest.append(now - rows[0][0])
    lat.sort()
    oldest.sort()

    def q(xs, p):
        return xs[min(len(xs) - 1, int(p * len(xs)))] if xs else float("nan")

    return {"updates_per_s_min": min(updates.values()) / seconds if updates else 0.0,
            "updates_per_s_max": max(updates.values()) / seconds if updates else 0.0,
            "boxes_updated": len(updates), "latency_p50_s": q(lat, 0.5), "latency_p99_s": q(lat, 0.99),
            "latency_max_s": q(lat, 1.0), "latency_samples": len(lat),
            "wait_p50_s": q(oldest, 0.5), "wait_p99_s": q(oldest, 0.99), "wait_max_s": q(oldest, 1.0)}


def run_one(n_boxes: int, sample_hz: float, seconds: float, workdir: Path, warmup_s: float = 3.0) -> dict:
    keys = {s: os.urandom(32) for s in range(FIRST_SYSID, FIRST_SYSID + n_boxes)}
    box_args = []
    for s, k in keys.items():
        write_key(workdir / f"box{s}.key", k, overwrite=True)
        box_args += ["--box", f"{s}:{workdir / f'box{s}.key'}"]
    port = _free_udp_port()
    archive = workdir / f"archive-{sample_hz:g}.sqlite"
    root = Path(__file__).resolve().parents[1]
    proc = subprocess.Popen([sys.executable, "-m", "ground.station", f"udpin:127.0.0.1:{port}", *box_args,
                             "--web", "127.0.0.1:0", "--archive", str(archive), "--quiet"], cwd=root,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    stop = threading.Event()
    sent = [0]
    try:
        line = proc.stdout.readline()
        if not line.startswith("web view: "):
            raise RuntimeError(f"ground.station did not start: {line}{proc.stderr.read()}")
        url = line.split()[-1]
        boxes = [SyntheticBox(s, k) for s, k in keys.items()]
        sender = threading.Thread(target=_send, args=(boxes, port, sample_hz, stop, sent), daemon=True)
        sender.start()
        cpu0, t0 = _cpu_s(proc.pid), time.monotonic()
        sent0 = [0]

        async def measure():
            await asyncio.sleep(warmup_s)
            sent0[0] = sent[0]
            return await _watch(url, seconds, 0.0)

        result = asyncio.run(measure())
        cpu = (_cpu_s(proc.pid) - cpu0) / (time.monotonic() - t0)
        frames_per_s = (sent[0] - sent0[0]) / seconds
        rss = _rss_MB(proc.pid)
    finally:
        stop.set()
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=120)
    archived = next((int(x.split()[1]) for x in out.splitlines() if x.startswith("archived ")), 0)
    return {"boxes": n_boxes, "sample_hz": sample_hz, "seconds": seconds, "frames_per_s": frames_per_s,
            "frames_sent": sent[0], "frames_archived": archived, "station_cpu_share": cpu,
            "station_rss_MB": rss, **result,
            "dropped": "dropped" in out, "station_exit": proc.returncode}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.station_load", description=__doc__.splitlines()[0])
    ap.add_argument("--boxes", type=int_range(1, 32), default=10, help="boxes at once (default 10)")
    ap.add_argument("--sample-hz", type=finite_float(0.1, 1000), nargs="+", default=[33.0], metavar="HZ",
                    help="samples a second per box (default 33: about 100 frames/s a box, a box's telemetry at "
                         "its default 20 samples/s with all its estimators)")
    ap.add_argument("--seconds", type=finite_float(1, 3600), default=20.0, help="measured per rate (default 20)")
    ap.add_argument("--json", metavar="FILE", help="write the results as JSON (docs/station_load.json)")
    args = ap.parse_args(argv)
    runs = []
    with tempfile.TemporaryDirectory(prefix="station-load-") as tmp:
        for hz in args.sample_hz:
            r = run_one(args.boxes, hz, args.seconds, Path(tmp))
            runs.append(r)
            print(f"{args.boxes} boxes × {hz:g} samples/s: {r['frames_per_s']:.0f} frames/s sent, "
                  f"{r['updates_per_s_min']:.2f}–{r['updates_per_s_max']:.2f} updates/s per box, latency p50 "
                  f"{r['latency_p50_s'] * 1e3:.0f} ms p99 {r['latency_p99_s'] * 1e3:.0f} ms max "
                  f"{r['latency_max_s'] * 1e3:.0f} ms (oldest sample of an update: p99 {r['wait_p99_s'] * 1e3:.0f} ms, "
                  f"max {r['wait_max_s'] * 1e3:.0f} ms); station CPU {100 * r['station_cpu_share']:.0f} % of a core, "
                  f"{r['station_rss_MB']:.0f} MB; archived {r['frames_archived']} of {r['frames_sent']}")
    if args.json:
        doc = {"command": "python -m bench.station_load " + " ".join(argv if argv is not None else sys.argv[1:]),
               "machine": {"date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()), "cpus": os.cpu_count(),
                           "load_average_1_5_15": list(os.getloadavg())},
               "runs": runs}
        Path(args.json).write_text(json.dumps(doc, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
