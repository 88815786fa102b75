"""Property-based fuzz of every command-line tool's arguments: fsw.main (target), hil.sitl, ground.replay,
ground.decode, ground.estimate (rates and --inertia), ground.inertia, ground.command, ground.keys,
bench.soak, bench.accuracy, bench.inertia, bench.deorbit, hil.pty_link and fsw.telemetry.dialect.

Each argv is built from the tool's real options (`SPECS`, checked against the parser the tool builds:
`test_the_specs_name_every_option`) with values drawn from valid and hostile ones: empty, NaN, ±inf,
-1, 0, out of range, 1e308, huge integers, non-ASCII, paths to missing directories, to a directory,
to a FIFO, to the input file, the same output twice, broken scenario and key files, unknown options.
Every value carries the oracle's verdict on it, independent of the tool: valid, invalid, or unknown
(where the tool's cross-checks decide). The property: `main(argv)` returns or exits with 0, 1, 2 or
130 (ground.command also 3, "no answer", its documented status) — never another exception, never a
traceback on stderr; a non-zero status says why on stderr; an argv the oracle calls invalid does not
exit 0 and never reaches the heavy work; a refusal (2) writes no output; no input file changes.

The heavy work is stubbed (`Tool.stubs`: the simulator, the loop, the fits, the link): a stub records
that the front door let the arguments in. Each property is two tests (`support.tiers`): the fast one
and ``*_fuzz``, marked slow, with 10,000 examples (``pytest -m slow tests/test_fuzz_cli.py``).
"""
from __future__ import annotations

import argparse
import contextlib
import io
import os
import re
import shutil
import signal
import stat
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
from hypothesis import strategies as st
from support import free_udp_port, good_tlog, tiers

import bench.accuracy
import bench.deorbit
import bench.inertia
import bench.soak
import fsw.main
import fsw.telemetry.dialect
import ground.command
import ground.decode
import ground.estimate
import ground.inertia
import ground.keys
import ground.plot
import ground.replay
import ground.station
import hil.pty_link
import hil.sim
import hil.sitl
from ground.recording import Recording, write_recording
from hil import scenario as scenarios

# --- the files every example starts from -------------------------------------------------------------


def _recording_csv() -> bytes:
    t = np.arange(40.0)
    b = np.column_stack([np.cos(0.1 * t), np.sin(0.1 * t), np.full_like(t, 0.5)]) * 40e-6
    m = np.zeros((40, 3))
    m[10:20, 0] = 0.2
    w = np.tile([0.01, 0.02, 0.03], (40, 1))
    import tempfile
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "r.csv"
        write_recording(p, Recording(t, b, m_Nm=m, w_ref_radps=w, metadata={
            "orbit_altitude_km": "500", "orbit_inclination_deg": "97", "orbit_raan_deg": "0",
            "orbit_arg_lat0_deg": "0", "field_epoch_year": "2025"}))
        return p.read_bytes()


KEY_HEX = bytes(range(7, 39)).hex()
ISOI = scenarios.resolve("isoi").read_text()
FILES: dict[str, tuple[bytes, int]] = {  # name: (content, mode)
    "good.tlog": (good_tlog(30), 0o644),
    "rec.csv": (_recording_csv(), 0o644),
    "empty.csv": (b"# nothing\nt_s,bx_uT,by_uT,bz_uT\n", 0o644),
    "notrec.csv": (b"hello, world\n", 0o644),
    "good.key": (KEY_HEX.encode() + b"\n", 0o600),
    "open.key": (KEY_HEX.encode() + b"\n", 0o644),
    "zero.key": (b"00" * 32 + b"\n", 0o600),
    "long.key": (KEY_HEX.encode() + b"\n" + b" " * 5000 + b"x\n", 0o600),
    "copy.toml": (ISOI.encode(), 0o644),
    "deorbit.toml": (scenarios.resolve("amds_deorbit").read_bytes(), 0o644),
    "broken.toml": (b"[body\nmass_kg = [[\n", 0o644),
    "huge.toml": (ISOI.replace("mass_kg = 5.5", "mass_kg = 1" + "0" * 400).encode(), 0o644),
    "realdir/rec.csv": (_recording_csv(), 0o644),
    "magcal.json": (b'{"hard_iron_uT": [1.5, -2, 0.5], "soft_iron": [[0.01, 0, 0], [0, -0.02, 0.003], [0, 0.003, 0]]}',
                    0o644),
    "badcal.json": (b'{"hard_iron_uT": [1.5, -2], "soft_iron": [[2, 0, 0], [0, 1, 0], [0, 0, 1]]}', 0o644),
}
DIRS = ("dir", "emptydir", "realdir")


def make_files(root: Path) -> None:
    """The fixture files in `root` (made again for every example: a tool may not change them)."""
    if root.exists():
        shutil.rmtree(root)
    root.mkdir(parents=True)
    for d in DIRS:
        (root / d).mkdir()
    (root / "dir" / "a.csv").write_bytes(FILES["rec.csv"][0])
    for name, (content, mode) in FILES.items():
        p = root / name
        p.write_bytes(content)
        p.chmod(mode)
    os.mkfifo(root / "fifo")
    (root / "link.csv").symlink_to(root / "rec.csv")


def snapshot(root: Path) -> dict[str, tuple]:
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in filenames + dirnames:
            p = Path(dirpath) / name
            st_ = os.lstat(p)
            content = p.read_bytes() if stat.S_ISREG(st_.st_mode) else None
            out[str(p.relative_to(root))] = (stat.S_IFMT(st_.st_mode), stat.S_IMODE(st_.st_mode), content,
                                             st_.st_mtime_ns if stat.S_ISREG(st_.st_mode) else None)
    return out


# --- values and the oracle's verdict on them --------------------------------------------------------

#: a value: (text, verdict) with verdict True (valid), False (invalid) or None (the tool decides). Text
#: may hold {files} and {out} (the example's folders), {port} (a free UDP port), and the tokens
#: "=INPUT" (the path of this argv's input) and "=OUTPUT" (the path of another output of this argv).
Value = tuple[str, bool | None]

NUMBERS = [-1e308, -1e6, -1.0, -1e-300, 0.0, 1e-300, 1e-3, 0.01, 0.5, 1.0, 2.0, 10.0, 100.0, 119.5, 120.0, 1000.0,
           1000.5, 3600.0, 3600.5, 1e6, 1e308]
NOT_NUMBERS: list[Value] = [("nan", False), ("NaN", False), ("inf", False), ("-inf", False), ("Infinity", False),
                            ("1e999", False), ("-1e999", False), ("", False), ("abc", False), ("0x10", False),
                            ("1,5", False), ("--", False), ("1_000", None), ("\u0661", None), (" 5 ", None),
                            ("１", None), ("2" * 400, None)]


def floats(lo: float | None = None, hi: float | None = None, lo_open: bool = False, hi_open: bool = False
           ) -> list[Value]:
    """Numbers for an option that takes a finite float in [lo, hi] (open ends when `*_open`)."""
    def ok(x):
        return (lo is None or (x > lo if lo_open else x >= lo)) and (hi is None or (x < hi if hi_open else x <= hi))
    return [(repr(x), ok(x)) for x in NUMBERS] + NOT_NUMBERS


def ints(lo: int | None = None, hi: int | None = None) -> list[Value]:
    """Numbers for an option that takes a whole number in [lo, hi]."""
    cands = [-1, 0, 1, 2, 3, 12, 100, 255, 256, 65535, 65536, 2**31, 2**63, 10**30, 10**400]

    def ok(x):
        return (lo is None or x >= lo) and (hi is None or x <= hi)
    return [(str(x), ok(x)) for x in cands] + [
        ("1.5", False), ("nan", False), ("", False), ("abc", False), ("1e3", False), ("0x10", False),
        ("9" * 5000, False), ("-9" * 3, False), (" 7", None), ("\u0661", None)]


def choices(cs) -> list[Value]:
    bad = [("", False), ("nosuch", False)] + [(c.upper(), False) for c in cs if c.upper() not in cs]
    return [(c, True) for c in cs] + bad


FLAG: list[Value] = [("", True)]
#: a recording-format CSV to read
IN_RECORDING: list[Value] = [("{files}/rec.csv", True), ("{files}/link.csv", True), ("{files}/missing.csv", False),
                             ("{files}/nodir/x.csv", False), ("{files}/dir", False), ("{files}/notrec.csv", False),
                             ("{files}/empty.csv", False), ("", False), ("{files}/good.tlog", False)]
#: a file to write (an output)
OUT: list[Value] = [("{out}/a.out", True), ("{out}/b.out", True), ("{out}/é ü.out", True),
                    ("{files}/nodir/x.out", False), ("{files}/dir", False), ("{files}/fifo", False),
                    ("=INPUT", False), ("=OUTPUT", False), ("{files}/link.csv", None)]
PNG: list[Value] = [("{out}/p.png", True), ("{out}/p.svg", True), ("{out}/p.xyz", False), ("{out}/p", False),
                    ("{files}/nodir/p.png", False), ("{files}/dir", False), ("=INPUT", False), ("=OUTPUT", False)]
KEY: list[Value] = [("{files}/good.key", True), ("{files}/open.key", False), ("{files}/zero.key", False),
                    ("{files}/long.key", False), ("{files}/missing.key", False), ("{files}/dir", False),
                    ("{files}/fifo", False), ("{files}/rec.csv", False), ("", False)]
SCENARIO: list[Value] = [("isoi", True), ("aist2d", True), ("{files}/copy.toml", True), ("nosuch", False),
                         ("ISOI", False), ("", False), ("{files}/missing.toml", False), ("{files}/broken.toml", False),
                         ("{files}/huge.toml", False), ("{files}/dir", False), ("{files}/fifo", False),
                         ("{files}/rec.csv", False)]
#: a host-magnetics calibration (JSON) to read
MAGCAL: list[Value] = [("{files}/magcal.json", True), ("{files}/badcal.json", False), ("{files}/rec.csv", False),
                       ("{files}/missing.json", False), ("{files}/dir", False), ("{files}/fifo", False), ("", False)]
DEORBIT_SCENARIO: list[Value] = [("amds_deorbit", True), ("{files}/deorbit.toml", True)] + \
    [(t, False) for t, _ in SCENARIO]
URL_OUT: list[Value] = [("udpout:127.0.0.1:9", True), ("udpout:localhost:9", True), ("udpout:127.0.0.1:0", False),
                        ("udpout:127.0.0.1:99999", False), ("udpout:127.0.0.1:-1", False), ("udpout:nohost", False),
                        ("udpout::9", False), ("tcp:127.0.0.1:abc", False), ("udpout:127.0.0.1:", False),
                        ("{files}/missing-serial", None)]
URL_IN: list[Value] = [("udpin:127.0.0.1:{port}", True), ("udpin:0.0.0.0:99999", False), ("udpin:127.0.0.1:0", False),
                       ("udpin:nohost", False)]
TEXT: list[Value] = [("", None), ("x", None), ("é", None), ("-x", None), ("a,b", None), (" ", None), ("\u2028", None),
                     ("x" * 5000, None)]


@dataclass
class Opt:
    values: list
    role: str = ""  # "in", "out" (an output path), "" (anything else)
    nargs: int = 1  # 0: a flag; 2: two values (each value a tuple of two texts)
    required: bool = False
    repeat: bool = False  # action="append"


@dataclass
class Tool:
    name: str
    main: Callable
    options: dict[str, Opt]
    positionals: list[tuple[str, Opt]] = field(default_factory=list)
    stubs: list[str] = field(default_factory=list)  # "module:attribute" replaced by a stub that records
    statuses: frozenset = frozenset({0, 1, 2, 130})
    judge: Callable | None = None  # (verdict, chosen values) -> verdict, for the tool's cross-checks
    probe: tuple = ()  # argv that makes main build the parser of this spec


def flag() -> Opt:
    return Opt(FLAG, nargs=0)


#: --magcal and --estimate-magcal (which needs the recording's orbit and enough of a tumble: the tool decides),
#: --no-magcal (not the recording's calibration): one of them at most
# every Monte-Carlo benchmark's (bench.campaign.options); the judge: _campaign_judge
CAMPAIGN_OPTIONS = {"--workers": Opt(ints(1, 1024)),
                    "--scheduler": Opt([("tcp://127.0.0.1:8786", True), ("tcp://[::1]:1", True),
                                        ("127.0.0.1:8786", False), ("", False)]),
                    "--results": Opt(OUT, role="out"), "--rerun": Opt([("r1", True), ("a/b#0", True)]),
                    "--no-progress": flag()}
MAGCAL_OPTIONS = {"--magcal": Opt(MAGCAL, role="in"), "--estimate-magcal": Opt([("", None)], nargs=0),
                  "--no-magcal": flag()}


# --- the tools --------------------------------------------------------------------------------------

TLE1 = "1 25544U 98067A   26325.50000000  .00016717  00000-0  10270-3 0  9000"
TLE2 = "2 25544  51.6400 208.9163 0006317  69.9862  25.2906 15.50000000    09"
#: the orbit on the command line (over the recording's metadata) and the field's turn allowed for without one
ORBIT_OPTIONS = {
    "--tle": Opt([((TLE1, TLE2), True), (("1", "2"), False), ((TLE2, TLE1), False), (("", ""), False)], nargs=2),
    "--utc0": Opt([("2025-06-15T12:00:00", True), ("2025-06-15", True), ("yesterday", False), ("", False),
                   ("2025-13-45T99:00", False)]),
    "--field-turn-dps": Opt(floats(0)),
}


def _target_judge(v, chosen):
    buses = [o for o in ("--mag-serial", "--mag-i2c", "--mag-spi") if o in chosen]
    if len(buses) != 1:  # one bus, or the configuration's (every --config drawn here is refused)
        return False
    return v


def _magcal_judge(v, chosen):
    if sum(o in chosen for o in ("--magcal", "--estimate-magcal", "--no-magcal")) > 1:  # one of them at most
        return False
    return v


def _estimate_judge(v, chosen):
    v = _magcal_judge(v, chosen)
    if "--tle" in chosen and "--utc0" not in chosen:
        return False
    if "--tle" in chosen and "--scenario" in chosen:
        return False
    return v


def _command_judge(v, chosen):
    if "--list" in chosen:  # the list, whatever else is asked: only argparse's own checks count
        return _without(chosen, "url", "command", "params", "--set-param", "--get-param", "--key")
    if "url" not in chosen and "command" in chosen:  # the command word is taken for the URL (a serial device)
        return None if v is not False else _without(chosen, "command", "params")
    if "command" not in chosen and "params" in chosen:  # the first parameter is taken for the command
        return None if v is not False else _without(chosen, "params")
    if "url" not in chosen or not ({"command", "--set-param", "--get-param"} & set(chosen)):
        return False
    if sum(x in chosen for x in ("command", "--set-param", "--get-param")) > 1:
        return False
    return v


def _keys_judge(v, chosen):
    action = chosen.get("action", ("", False))[0]
    if action not in ("new", "fingerprint"):
        return False
    if action == "fingerprint":
        if "--force" in chosen:
            return False
        key = chosen.get("file", ("", False))[0]
        return {"{files}/good.key": True}.get(key, False)
    target = chosen.get("file", ("", False))[0]
    if target.startswith("{files}/") and target.removeprefix("{files}/") in FILES:
        return v if "--force" in chosen else False  # an existing file is replaced only with --force
    return v


def _accuracy_judge(v, chosen):
    if "--real" in chosen:
        return _without(chosen, "--rows", "--methods", "--runs", "--record-samples", "--warmup-s", "--workers",
                        "--quick", "--seed")
    if "--quick" in chosen:  # two rows of its own, one short run each
        return _without(chosen, "--rows", "--runs", "--record-samples", "--warmup-s")
    return v


def _inertia_bench_judge(v, chosen):
    if "--crb" in chosen:
        return _without(chosen, "--duration", "--fits", "--runs", "--no-linear", "--shape-data", "--quick")
    if "--quick" in chosen:
        return _without(chosen, "--duration")
    return v


def _campaign_judge(v, chosen):
    """bench.campaign.options: --workers sizes a local cluster (not with --scheduler); --rerun needs --results."""
    if v and "--scheduler" in chosen and "--workers" in chosen:
        return False
    if v and "--rerun" in chosen and "--results" not in chosen:
        return False
    return v


def _deorbit_judge(v, chosen):
    """One run (no --sweep) keeps no results file and re-runs nothing."""
    v = _campaign_judge(v, chosen)
    if v and "--sweep" not in chosen and ("--results" in chosen or "--rerun" in chosen):
        return False
    return v


def _without(chosen, *names):
    """The verdict on the values without `names` (options the tool does not use in this mode)."""
    return verdict({k: x for k, x in chosen.items() if k not in names})


def verdict(chosen) -> bool | None:
    vs = [x[1] for x in chosen.values()]
    return False if False in vs else None if None in vs else True


#: the options every run of the flight software takes (fsw.config.add_run_options)
RUN_OPTIONS = {
    "--duration": Opt(floats(0, lo_open=True)),
    "--rate": Opt(floats(0, 1000, lo_open=True)),
    "--link": Opt(URL_OUT),
    "--baud": Opt(ints(1)),
    "--key": Opt(KEY, role="in"),
    "--uplink": Opt(URL_IN + [(u, False) for u, ok in URL_OUT if ok is False]),
    "--buffer-frames": Opt(ints(0, 1_000_000)),
    "--sample-store": Opt(OUT, role="out"),
    "--sample-rate": Opt(floats(0, 1000, lo_open=True)),
    "--sigma-uT": Opt(floats(0, 1000, lo_open=True)),
    "--max-sample-tlm-hz": Opt(floats(0.01, 1000)),
    "--rate-filter": Opt(choices(("euler", "mm", "orbit", "fixed"))),
    "--fixed-sample-rate": flag(),
    "--quiet": flag(),
}


SPECS: list[Tool] = [
    Tool("fsw.main", fsw.main.main, {
        "--mag-serial": Opt([("{files}/missing-serial", None), ("{files}/rec.csv", None), ("/dev/null", None),
                             ("{files}/fifo", None), ("", False)], role="in"),
        "--mag-i2c": Opt([("{files}/missing-i2c", None), ("/dev/null", None), ("{files}/dir", None), ("", False)],
                         role="in"),
        "--mag-spi": Opt([("/dev/spidev0.0", None), ("/dev/i2c-1", False), ("{files}/rec.csv", False), ("", False)],
                         role="in"),
        "--config": Opt([("{files}/missing.toml", False), ("{files}/broken.toml", False), ("{files}/copy.toml", False),
                         ("{files}/dir", False), ("{files}/fifo", False), ("{files}/rec.csv", False), ("", False)],
                        role="in"),
        "--system-id": Opt(ints(1, 255)),
        "--state-dir": Opt([("{files}/dir", None), ("{files}/missing-dir", False), ("{files}/rec.csv", False)]),
        "--tle-file": Opt(OUT, role="out"),
        "--tle-max-age": Opt(floats(0.1, 365)),
        **RUN_OPTIONS,
    }, stubs=["fsw.drivers.serial_bus:SerialBus", "fsw.drivers.i2c_bus:I2cBus"], judge=_target_judge),
    Tool("hil.sitl", hil.sitl.main, {
        "--scenario": Opt(SCENARIO + [("amds_deorbit", True)], role="in"),
        "--speed": Opt(floats(0)),
        "--seed": Opt(ints(0)),
        "--ident-inertia-guess": Opt(floats(0, lo_open=True)),
        "--work-clock": Opt(choices(("cpu", "wall"))),
        "--system-id": Opt(ints(1, 255)),
        **RUN_OPTIONS,
    }, stubs=["fsw.system:FlightSoftware"]),
    Tool("ground.station", ground.station.main, {
        "--baud": Opt(ints(1)),
        "--key": Opt(KEY, role="in"),
        "--box": Opt([("1:{files}/good.key", True), ("7:{files}/good.key", True), ("0:{files}/good.key", False),
                      ("256:{files}/good.key", False), ("1:{files}/open.key", False), ("1:{files}/missing.key", False),
                      ("1", False), ("x:{files}/good.key", False), ("1:", False), ("", False)], repeat=True),
        "--web": Opt([("127.0.0.1:0", True), ("localhost:8080", True), ("[::1]:0", True), ("8080", False),
                      ("127.0.0.1:99999", False), ("127.0.0.1:x", False), (":80", False), ("", False)]),
        "--archive": Opt(OUT, role="out"),
        "--no-archive": flag(),
        "--method": Opt(choices(["boer", "derivative", "kalman"])),
        "--window": Opt(floats(0.5, 240)),
        "--duration": Opt(floats(0, lo_open=True)),
        "--quiet": flag(),
    }, positionals=[("links", Opt([("udpin:127.0.0.1:{port}", True), ("udpin:127.0.0.1:99999", False), ("", False),
                                   ("{files}/good.tlog", False), ("udpin:nohost", False), ("/dev/nosuch", None)],
                                  role="in", required=True))],
        stubs=["ground.station:Fleet"]),
    Tool("ground.replay", ground.replay.main, {
        "--rates-out": Opt(OUT, role="out"),
        "--kit-raw": flag(),
        **RUN_OPTIONS,
    }, positionals=[("input", Opt(IN_RECORDING, role="in"))], stubs=["fsw.system:FlightSoftware"]),
    Tool("ground.decode", ground.decode.main, {
        "--baud": Opt(ints(1)),
        "--tlog": Opt(OUT, role="out"),
        "--csv": Opt(OUT, role="out"),
        "--rates-csv": Opt(OUT, role="out"),
        "--method": Opt(choices(sorted(ground.decode.sent_methods()))),
        "--duration": Opt(floats(0, lo_open=True)),
        "--count": Opt(ints(1)),
        "--quiet": flag(),
        "--key": Opt(KEY, role="in"),
        "--no-resend": flag(),
        "--uplink": Opt(URL_OUT),
        "--archive": Opt(OUT, role="out"),
        "--no-archive": flag(),
    }, positionals=[("url", Opt([("{files}/good.tlog", True), ("udpin:127.0.0.1:{port}", True),
                                 ("{files}/missing.tlog", False), ("{files}/rec.csv", False),
                                 ("{files}/empty.csv", False), ("udpin:127.0.0.1:99999", False), ("", False),
                                 ("{files}/nodir/x.tlog", False), ("/dev/nosuch", False)],
                                role="in", required=True))],
        stubs=["ground.decode:run"]),
    Tool("ground.estimate", ground.estimate.main, {
        "--rates": Opt(OUT, role="out", required=True),
        "--method": Opt(choices(ground.estimate.METHODS)),
        "--plot": Opt(PNG, role="out"),
        "--sigma-uT": Opt(floats(0, 1000, lo_open=True)),
        "--decimate-hz": Opt(floats(0, lo_open=True)),
        "--scenario": Opt(SCENARIO, role="in"),
        **ORBIT_OPTIONS,
        "--known-inertia": Opt([("1,1,1", True), ("175,200,285", True), ("1,0,0,0,1,0,0,0,1", True),
                                ("nan,1,1", False), ("1,1,3", False), ("1,2", False), ("-1,1,1", False), ("a", False),
                                ("1,0.5,0,0,1,0,0,0,1", False), ("1e308,1e308,1e308", None), ("", False)]),
        **MAGCAL_OPTIONS,
        "--kit-raw": flag(),
    }, positionals=[("input", Opt(IN_RECORDING, role="in", required=True))],
        stubs=["ground.estimate:estimate", "ground.plot:plot_rates"], judge=_estimate_judge),
    Tool("ground.estimate --inertia", ground.estimate.main, {
        "--inertia": Opt(OUT, role="out", required=True),
        "--scenario": Opt(SCENARIO, role="in"),
        "--sigma-uT": Opt(floats(0, 1000, lo_open=True)),
        "--diag": flag(),
        "--guess": Opt(floats(0, lo_open=True)),
        "--hold": Opt(choices(["centered", "forward"])),
        "--plot": Opt(PNG, role="out"),
        "--running": Opt(ints(1)),
        "--quiet": flag(),
        **MAGCAL_OPTIONS,
        "--kit-raw": flag(),
        "--field-error": flag(),
        **ORBIT_OPTIONS,
    }, positionals=[("input", Opt(IN_RECORDING, role="in", required=True))],
        stubs=["ground.inertia:run"], probe=("--inertia",), judge=_estimate_judge),
    Tool("ground.inertia", ground.inertia.main, {
        "--scenario": Opt(SCENARIO, role="in"),
        "--sigma-uT": Opt(floats(0, 1000, lo_open=True)),
        "--diag": flag(),
        "--guess": Opt(floats(0, lo_open=True)),
        "--hold": Opt(choices(["centered", "forward"])),
        "--plot": Opt(PNG, role="out"),
        "--running": Opt(ints(1)),
        "--quiet": flag(),
        **MAGCAL_OPTIONS,
        "--kit-raw": flag(),
        "--field-error": flag(),
        **ORBIT_OPTIONS,
    }, positionals=[("input", Opt(IN_RECORDING, role="in", required=True)),
                    ("output", Opt(OUT, role="out", required=True))],
        stubs=["ground.inertia:run"], judge=_estimate_judge),
    Tool("ground.command", ground.command.main, {
        "--key": Opt(KEY, role="in"),
        "--set-param": Opt([(("TLM_SAMPLE_HZ", "5"), True), (("TLM_SAMPLE_HZ", "nan"), None),
                            (("TLM_SAMPLE_HZ", "1e39"), False), (("ÄBC", "1"), False), (("A" * 17, "1"), False),
                            (("", "1"), False), (("X", "abc"), False), (("X", "inf"), False)], nargs=2),
        "--get-param": Opt([("TLM_SAMPLE_HZ", True), ("X", True), ("ÄBC", False), ("A" * 17, False), ("", False)]),
        "--target": Opt([("1/191", True), ("0/0", True), ("255/255", True), ("1/999", False), ("1", False),
                         ("a/b", False), ("", False), ("1/2/3", False), ("-1/2", False), ("²/1", False)]),
        "--timeout": Opt(floats(0, 3600, lo_open=True)),
        "--retries": Opt(ints(0, 100)),
        "--wait": Opt(floats(0, 3600)),
        "--baud": Opt(ints(1)),
        "--list": flag(),
    }, positionals=[("url", Opt([("udpout:127.0.0.1:9", True), ("udpin:127.0.0.1:{port}", True),
                                 ("udpout:127.0.0.1:99999", False), ("udpout:nohost", False)], required=True)),
                    ("command", Opt([("capsule", True), ("DEBRIS_CAPSULE", True), ("MAV_CMD_DEBRIS_CAPSULE", True),
                                     ("400", True), ("0", True), ("65535", True), ("70000", False),
                                     ("nosuch", False), ("", False), ("1.5", False), ("time", None),
                                     ("tle", None)])),
                    ("params", Opt([("0", True), ("1", True), ("nan", True), ("-1", True), ("channel=0", True),
                                    ("param7=1", True), ("1e39", False), ("abc", False), ("param9=1", False),
                                    ("nolabel=1", False), ("inf", False), ("=1", False)]))],
        stubs=["ground.command:Session"], statuses=frozenset({0, 1, 2, 3, 130}), judge=_command_judge),
    Tool("ground.keys", ground.keys.main, {"--force": flag()},
         positionals=[("action", Opt([("new", True), ("fingerprint", True), ("old", False), ("", False)],
                                     required=True)),
                      ("file", Opt([("{out}/k.key", True), ("{files}/good.key", True), ("{files}/rec.csv", True),
                                    ("{files}/nodir/k.key", False), ("{files}/dir", False), ("{files}/fifo", False),
                                    ("{files}/link.csv", False), ("{files}/open.key", True),
                                    ("{files}/zero.key", True), ("", False)], role="out", required=True))],
         judge=_keys_judge, probe=("new", "x")),
    Tool("bench.soak", bench.soak.main, {
        "--duration": Opt(floats(120)),
        "--json": Opt(OUT, role="out"),
        "--seed": Opt(ints(0)),
        "--scenario": Opt(SCENARIO, role="in"),
        "--rate": Opt(floats(0, 1000, lo_open=True)),
        "--quiet": flag(),
        **CAMPAIGN_OPTIONS,
    }, stubs=["bench.soak:run", "bench.campaign.options:execute"], judge=_campaign_judge),
    Tool("bench.accuracy", bench.accuracy.main, {
        "--json": Opt(OUT, role="out"),
        "--runs": Opt(ints(1, 1000)),
        "--seed": Opt(ints(0)),
        "--record-samples": Opt(ints(3)),
        "--warmup-s": Opt(floats(0)),
        **CAMPAIGN_OPTIONS,
        "--rows": Opt([("", True), ("undirected", True), ("zzz", False)] + TEXT[1:]),
        "--methods": Opt([("", True), ("boer", True), ("kalman,smoother", True), ("nosuch", False),
                          ("boer,nosuch", False), (",", None)]),
        "--quick": flag(),
        "--real": Opt([("{files}/realdir", True), ("{files}/missing", False), ("{files}/emptydir", False),
                       ("{files}/rec.csv", False), ("", False), ("{files}/fifo", False)], role="in"),
        "--max-s": Opt(floats(0, lo_open=True)),
        "--world": Opt(choices(["dipole", "igrf", "both", "igrf_exact"])),
        "--host-drift": Opt(choices(["untracked", "tracked"])),
    }, stubs=["bench.campaign.options:execute", "bench.accuracy:real_recordings"],
        judge=lambda v, chosen: _campaign_judge(_accuracy_judge(v, chosen), chosen)),
    Tool("bench.inertia", bench.inertia.main, {
        "--json": Opt(OUT, role="out"),
        "--runs": Opt(ints(2)),
        "--seed": Opt(ints(0)),
        "--duration": Opt([("auto", True)] + floats(120)),
        "--scenarios": Opt([("isoi", True), ("aist2d,isoi", True), (" isoi , aist2d ", True), ("", False),
                            (",", False), ("nosuch", False), ("isoi,nosuch", False), ("{files}/copy.toml", True),
                            ("{files}/broken.toml", False)]),
        "--quick": flag(),
        "--no-linear": flag(),
        "--fits": Opt([("full", True), ("shape", True), ("full,shape", True), ("", False), ("bogus", False),
                       ("full,bogus", False)]),
        "--shape-data": Opt(choices(["all", "free"])),
        "--world": Opt(choices(["ideal", "realistic"])),
        "--field-error": Opt(choices(["fit", "none"])),
        "--crb": Opt([("900", True), ("900,1800", True), ("", False), ("nan", False), ("0", False), ("a", False),
                      ("900,", False)]),
        **CAMPAIGN_OPTIONS,
    }, stubs=["bench.inertia:bench_scenario", "bench.inertia:truth_record", "bench.inertia:crb_table",
              "bench.campaign.options:execute"],
        judge=lambda v, chosen: _campaign_judge(_inertia_bench_judge(v, chosen), chosen)),
    Tool("bench.deorbit", bench.deorbit.main, {
        "--scenario": Opt(DEORBIT_SCENARIO, role="in"),
        "--duration": Opt(floats(0, lo_open=True)),
        "--rate": Opt(floats(1, 100)),
        "--arg-lat0": Opt(floats()),
        "--law": Opt(choices(["mpc", "paper"])),
        "--attitude": Opt(choices(["estimate", "truth"])),
        "--kit-calibration": Opt(choices(["handed-over", "none"])),
        "--seed": Opt(ints(0, 2**31 - 1)),
        "--sweep": flag(),
        "--starts": Opt(ints(1, 8)),
        "--seeds": Opt(ints(1, 100)),
        "--fault": Opt([("stall:pitch:1500", True), ("stuck:yaw:900:0.5", True), ("switch:yaw:600:closed=1", True),
                        ("gpio:1:10", True), ("", False), ("bogus", False), ("stall:pitch", False),
                        ("stall:roll:10", False), ("stall:pitch:nan", False), ("stall:pitch:inf", False),
                        ("stuck:yaw:900:nan", False), ("stall:pitch:abc", False), ("stall:pitch:-5", False)],
                       repeat=True),
        "--controller": Opt([("continuation_reweight=2", True), ("horizon=30", True), ("law=paper", True),
                             ("bogus=1", False), ("horizon", False), ("horizon=abc", False), ("horizon=1", False),
                             ("energy_price_per_J=nan", False), ("widths_s=80", False), ("law=bang", False)],
                            repeat=True),
        "--json": Opt(OUT, role="out"),
        "--plot": Opt(PNG, role="out"),
        **CAMPAIGN_OPTIONS,
    }, stubs=["fsw.system:FlightSoftware", "bench.campaign.options:execute"], judge=_deorbit_judge),
    Tool("hil.pty_link", hil.pty_link.main, {
        "--scenario": Opt(SCENARIO, role="in"),
        "--seed": Opt(ints(0)),
        "--duration": Opt(floats(0, lo_open=True)),
        "--corrupt-rate": Opt(floats(0, 1)),
        "--drop-rate": Opt(floats(0, 1)),
        "--quiet": flag(),
    }, stubs=["hil.sim:Simulator"]),
    Tool("fsw.telemetry.dialect", fsw.telemetry.dialect.main, {"--generate": flag()},
         stubs=["fsw.telemetry.dialect:generate"]),
]
TOOLS = {t.name: t for t in SPECS}


# --- the parser each tool builds (the spec is checked against it) ------------------------------------

class _Captured(Exception):
    pass


def parser_of(tool: Tool) -> argparse.ArgumentParser:
    """The parser `tool.main` builds, caught at its first parse."""
    seen = []
    real = argparse.ArgumentParser.parse_known_args

    def capture(self, args=None, namespace=None):
        seen.append(self)
        raise _Captured

    argparse.ArgumentParser.parse_known_args = capture
    try:
        tool.main(list(tool.probe))
    except _Captured:
        pass
    finally:
        argparse.ArgumentParser.parse_known_args = real
    return seen[0]


def parser_names(ap: argparse.ArgumentParser) -> tuple[set, list]:
    """(option strings, positional dests) of a parser, subcommands' included."""
    options, positionals = set(), []
    for a in ap._actions:
        if isinstance(a, argparse._HelpAction):
            continue
        if isinstance(a, argparse._SubParsersAction):
            positionals.append(a.dest)
            for sub in a.choices.values():
                o, p = parser_names(sub)
                options |= o
                positionals += [x for x in p if x not in positionals]
        elif a.option_strings:
            options.add(max(a.option_strings, key=len))
        else:
            positionals.append(a.dest)
    return options, positionals


@pytest.mark.parametrize("name", TOOLS)
def test_the_specs_name_every_option(name):
    """The fuzz knows every option of every tool: a new option must be given values here."""
    tool = TOOLS[name]
    options, positionals = parser_names(parser_of(tool))
    assert options == set(tool.options), f"{name}: options {options ^ set(tool.options)} differ"
    assert positionals == [p for p, _ in tool.positionals], f"{name}: positionals differ"


# --- argv ---------------------------------------------------------------------------------------------

@st.composite
def argvs(draw, tool: Tool):
    """(argv templates, {option or positional: (value, verdict)}, verdict on the whole argv)."""
    chosen: dict[str, tuple] = {}
    words: list[str] = []
    verdict_extra: bool | None = True
    pos_words = []
    for name, opt in tool.positionals:
        if not opt.required and not draw(st.booleans()):
            continue
        if opt.required and draw(st.integers(0, 15)) == 0:  # a required one left out
            continue
        text, ok = draw(st.sampled_from(opt.values))
        chosen[name] = (text, ok)
        pos_words.append(text)
    opt_words = []
    for name, opt in tool.options.items():
        if not (draw(st.integers(0, 15)) != 0 if opt.required else draw(st.integers(0, 3)) == 0):
            continue
        for _ in range(2 if opt.repeat and draw(st.booleans()) else 1):
            text, ok = draw(st.sampled_from(opt.values))
            if opt.repeat and name in chosen:
                ok = False if False in (ok, chosen[name][1]) else None if None in (ok, chosen[name][1]) else True
            chosen[name] = (text, ok)
            if opt.nargs == 0:
                opt_words.append([name])
            elif opt.nargs == 2:
                opt_words.append([name, *text])
            elif text.startswith("-") or draw(st.integers(0, 4)) == 0:
                opt_words.append([f"{name}={text}"])
            else:
                opt_words.append([name, text])
    extra = draw(st.sampled_from(["none"] * 6 + ["unknown", "help", "dash"]))
    if extra == "unknown":
        opt_words.append([draw(st.sampled_from(["--bogus", "--sitl=1", "-x", "--quiet=yes"]))])
        verdict_extra = False
    elif extra == "help":
        opt_words.append(["--help"])
    elif extra == "dash":
        pos_words.append("--")
        verdict_extra = None
    order = draw(st.permutations(range(len(opt_words))))
    opt_flat = [w for i in order for w in opt_words[i]]
    words = pos_words + opt_flat if draw(st.booleans()) and extra != "dash" else opt_flat + pos_words
    role = {n: o.role for n, o in tool.positionals + list(tool.options.items())}
    for name, (text, _ok) in list(chosen.items()):
        # "=INPUT" is an input only when this argv names an input file; "=OUTPUT", when another output
        if text == "=INPUT" and not any(role[n] == "in" and str(x[0]).startswith("{files}/")
                                        for n, x in chosen.items()):
            chosen[name] = (text, None)
        if text == "=OUTPUT" and not any(role[n] == "out" and n != name and str(x[0]).startswith("{out}/")
                                         for n, x in chosen.items()):
            chosen[name] = (text, None)
    v = verdict(chosen)
    missing = [n for n, o in tool.positionals + list(tool.options.items()) if o.required and n not in chosen]
    if missing and not (tool.name == "ground.command" and "--list" in chosen):
        v = False
    if tool.judge is not None:  # (it may find a value that is invalid in itself unused in this mode)
        v = tool.judge(v, chosen)
    v = False if verdict_extra is False else (None if verdict_extra is None and v else v)
    if extra == "help" and verdict_extra is True:
        v = None  # --help comes first or last: argparse exits 0 at it, or an error before it
    return words, chosen, v


# --- running a tool ----------------------------------------------------------------------------------

class Reached(BaseException):
    """A stub of the heavy work was called: the front door let the arguments in."""


class Hung(BaseException):
    pass


def role_of(tool: Tool, name: str) -> str:
    return (tool.options.get(name) or dict(tool.positionals)[name]).role


def _resolve(words: list[str], chosen: dict, tool: Tool, files: Path, out: Path, port: int) -> list[str]:
    role = {n: o.role for n, o in tool.positionals + list(tool.options.items())}
    inputs = [files / x[0].removeprefix("{files}/") for n, x in chosen.items()
              if role[n] == "in" and str(x[0]).startswith("{files}/")]
    outputs = [x[0] for n, x in chosen.items() if role[n] == "out" and str(x[0]).startswith("{out}/")]
    first_in = str(inputs[0]) if inputs else str(files / "rec.csv")
    other_out = outputs[0].format(out=out) if outputs else str(out / "other.out")
    return [w.replace("=INPUT", first_in).replace("=OUTPUT", other_out)
            .replace("{files}", str(files)).replace("{out}", str(out)).replace("{port}", str(port)) for w in words]


def _stub(reached: list):
    def stub(*args, **kwargs):
        reached.append(args)
        raise Reached
    return stub


def _decode_run(reached, real):
    """ground.decode.run: the real one on a tlog file (small), a stub on a live link."""
    def run(url, **kw):
        reached.append(url)
        if Path(url).is_file():
            return real(url, **kw)
        raise Reached
    return run


def _estimate(reached):
    def estimate(method, t, b, sigma, **kw):
        reached.append(method)
        n = len(t)
        return np.zeros((n, 3)), np.full((n, 3), 0.1), {}
    return estimate


def run_tool(tool: Tool, argv: list[str], monkeypatch: pytest.MonkeyPatch) -> tuple[int | str, str, list]:
    """(exit status, or "reached" when a stub of the heavy work was called; stderr; stub calls)."""
    reached: list = []
    for target in tool.stubs:
        module, attr = target.split(":")
        mod = __import__(module, fromlist=[attr])
        real = getattr(mod, attr)
        if target == "ground.decode:run":
            monkeypatch.setattr(mod, attr, _decode_run(reached, real))
        elif target == "ground.estimate:estimate":
            monkeypatch.setattr(mod, attr, _estimate(reached))
        elif target == "ground.plot:plot_rates":
            monkeypatch.setattr(mod, attr, lambda *a, **k: reached.append("plot"))
        else:
            monkeypatch.setattr(mod, attr, _stub(reached))
    err, out = io.StringIO(), io.StringIO()

    def hung(signum, frame):
        raise Hung

    old = signal.signal(signal.SIGALRM, hung)
    signal.setitimer(signal.ITIMER_REAL, 20.0)
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
            try:
                status = tool.main(argv)
            except SystemExit as e:
                status = e.code if isinstance(e.code, int) or e.code is None else 1
            except Reached:
                status = "reached"
    except Hung:
        raise AssertionError(f"{tool.name} {argv}: still running after 20 s (waiting on a FIFO?)") from None
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    return (0 if status is None else status), err.getvalue(), reached


def cli_property(tool: Tool):
    def prop(workdir, case):
        words, chosen, v = case
        files, out = workdir / "files", workdir / "out"
        if not files.exists() or snapshot(files) != FRESH.get(files):  # made again only when a tool changed them
            make_files(files)
            FRESH[files] = snapshot(files)
        if out.exists():
            shutil.rmtree(out)
        out.mkdir()
        argv = _resolve(words, chosen, tool, files, out, PORT)
        before = FRESH[files]
        with pytest.MonkeyPatch.context() as mp:
            status, err, _ = run_tool(tool, argv, mp)
        shown = f"{tool.name} {argv}: status {status}, stderr {err[-500:]!r}"
        assert "Traceback" not in err, shown
        assert not re.search(r"^\w+(Error|Exception|Interrupt)\b", err, re.M), shown
        if status != "reached":
            assert status in tool.statuses, shown
        if status not in (0, "reached"):
            assert err.strip(), f"{shown}: no reason given"
        if v is False:
            assert status not in (0, "reached"), f"{shown}: an invalid argv was let in ({chosen})"
        if status == 2:
            assert not any(out.iterdir()), f"{shown}: refused, but wrote {list(out.iterdir())}"
        after = snapshot(files)
        written = set()  # outputs named among the fixture files (ground.keys new FILE --force; through a link)
        for n, (text, _ok) in chosen.items():
            if v is not False and role_of(tool, n) == "out" and str(text).startswith("{files}/"):
                name = text.removeprefix("{files}/")
                written |= {name, os.path.relpath(os.path.realpath(files / name), files)}
        changed = {k for k in before.keys() | after.keys() if before.get(k) != after.get(k)} - written
        assert not changed, f"{shown}: changed {sorted(changed)}"
    prop.__name__ = f"cli_{tool.name.replace('.', '_').replace(' --', '_')}"
    return prop


PORT = free_udp_port()
FRESH: dict[Path, dict] = {}  # the snapshot of the fixture files as made


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return tmp_path_factory.mktemp("cli")


for _tool in SPECS:
    _fast, _slow = tiers(cli_property(_tool), case=argvs(_tool))
    _name = "test_cli_" + _tool.name.replace(".", "_").replace(" --", "_")
    globals()[_name], globals()[_name + "_fuzz"] = _fast, _slow
del _tool, _fast, _slow, _name
