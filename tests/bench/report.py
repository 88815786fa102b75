"""The speed table of docs/performance.md from a pytest-benchmark JSON file (`make bench` writes bench.json):

    python tests/bench/report.py bench.json

Medians per benchmark, the targets beside them, the Kalman step against filterpy's and the
ground decoder's throughput in frames per second.
"""
from __future__ import annotations

import json
import sys

#: frames per round of test_ground_parse (its docstring)
GROUND_FRAMES = 1000
LOOP_TARGET_US = 100.0
KALMAN_TARGET_RATIO = 3.0
GROUND_TARGET_FPS = 50_000


def table(bench: dict) -> str:
    med = {b["name"]: b["stats"]["median"] for b in bench["benchmarks"]}
    rows = ["| benchmark | median | target | holds |", "|---|---:|---|---|"]

    def row(name, value, target, ok):
        rows.append(f"| `{name}` | {value} | {target} | {'–' if ok is None else 'yes' if ok else 'NO'} |")

    if "test_loop_tick" in med:
        us = med["test_loop_tick"] * 1e6
        row("test_loop_tick", f"{us:.1f} µs", f"≤ {LOOP_TARGET_US:.0f} µs", us <= LOOP_TARGET_US)
    for name in ("test_driver_decode", "test_telemetry_encode"):
        if name in med:
            row(name, f"{med[name] * 1e6:.2f} µs", "–", None)
    if "test_kalman_step" in med and "test_filterpy_kalman_step" in med:
        ratio = med["test_filterpy_kalman_step"] / med["test_kalman_step"]
        row("test_kalman_step", f"{med['test_kalman_step'] * 1e6:.2f} µs",
            f"≥ {KALMAN_TARGET_RATIO:.0f}× faster than filterpy", ratio >= KALMAN_TARGET_RATIO)
        row("test_filterpy_kalman_step", f"{med['test_filterpy_kalman_step'] * 1e6:.2f} µs",
            f"ratio {ratio:.1f}×", ratio >= KALMAN_TARGET_RATIO)
    if "test_ground_parse" in med:
        fps = GROUND_FRAMES / med["test_ground_parse"]
        row("test_ground_parse", f"{med['test_ground_parse'] * 1e3:.1f} ms per {GROUND_FRAMES} frames "
            f"= {fps:,.0f} frames/s", f"≥ {GROUND_TARGET_FPS:,} frames/s", fps >= GROUND_TARGET_FPS)
    info = bench.get("machine_info", {})
    rows.append("")
    rows.append(f"{info.get('cpu', {}).get('brand_raw', 'unknown CPU')}, Python {info.get('python_version', '?')}, "
                f"{bench.get('datetime', '')[:10]}")
    return "\n".join(rows)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print(__doc__.strip(), file=sys.stderr)
        return 2
    with open(argv[0], encoding="utf-8") as f:
        print(table(json.load(f)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
