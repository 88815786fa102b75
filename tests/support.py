"""Helpers shared by the test modules (importable from tests/ and its sub-directories: tests/conftest.py
puts this directory on the path)."""
import functools
import math
import socket
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from fsw.telemetry.dialect import FSW_COMPID, FSW_SYSID, mavlink
from ground.decode import tlog_record

from fsw.system import NullLink  # noqa: F401  (the tests' null link is the benchmarks')


def free_udp_port() -> int:
    """A UDP port on the loopback that is free now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_udp_bound(port: int, timeout_s: float = 60.0) -> None:
    """Wait until another process has bound UDP `port` on the loopback (a decoder started in the
    background is listening): binding it ourselves then fails."""
    import errno
    import time

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError as e:
                if e.errno == errno.EADDRINUSE:
                    return
                raise
        time.sleep(0.05)
    raise TimeoutError(f"nothing bound UDP port {port} within {timeout_s:g} s")


class Capture:
    """A telemetry link that keeps what is written, as pymavlink's mavfile would send it."""

    def __init__(self):
        self.buf = bytearray()
        self.mav = mavlink.MAVLink(self, srcSystem=FSW_SYSID, srcComponent=FSW_COMPID)

    def write(self, b):
        self.buf += b

    def messages(self):
        return mavlink.MAVLink(None).parse_buffer(bytes(self.buf)) or []


def moment_recording(path, n: int, pulse: slice) -> Path:
    """A short recording with a known moment (0.2 N·m about x during `pulse`) and a circular orbit in its
    metadata: enough for ground.inertia to start, not to fit anything."""
    from ground.recording import Recording, write_recording

    t = np.arange(float(n))
    b = np.column_stack([np.cos(0.1 * t), np.sin(0.1 * t), np.full_like(t, 0.5)]) * 40e-6
    m = np.zeros((n, 3))
    m[pulse, 0] = 0.2
    write_recording(path, Recording(t, b, m_Nm=m, metadata={
        "orbit_altitude_km": "500", "orbit_inclination_deg": "97", "orbit_raan_deg": "0",
        "orbit_arg_lat0_deg": "0", "field_epoch_year": "2025"}))
    return Path(path)


def exit_status(main, argv) -> int:
    """A tool's exit status from its `main(argv)`, whether it returns it or argparse exits with it."""
    try:
        return main(argv)
    except SystemExit as e:
        return e.code if isinstance(e.code, int) else 1


#: the repository, and the optional laboratory recordings beside it (tests that read them skip without)
ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"

#: a body spinning at constant ω in a fixed field (`StubSource`)
W_RADPS = np.radians([6.0, -5.0, 6.5])
B_I_T = np.array([20e-6, -15e-6, 35e-6])


class StubSource:
    """Delivers the field of a body spinning at constant ω, one sample every `period_s`."""

    def __init__(self, period_s):
        self.period_s = period_s
        self.next_s = 0.0
        self.b_body_T = np.zeros(3)
        self.sample_time_s = float("nan")

    def update(self, now_s):
        if now_s + 1e-9 < self.next_s:
            return False
        self.sample_time_s = self.next_s
        self.b_body_T[:] = Rotation.from_rotvec(-W_RADPS * self.next_s).apply(B_I_T)
        self.next_s += self.period_s
        return True


class SteadySource:
    """A steady field (creeping by 10 nT a sample), one sample a second: the flight software's source for
    tests of its commands and services."""

    def __init__(self):
        self.b_body_T = np.array([20e-6, -10e-6, 30e-6])
        self.sample_time_s = math.nan
        self._next = 0.0

    def update(self, now_s):
        if now_s + 1e-9 < self._next:
            return False
        self.sample_time_s = self._next
        self.b_body_T = self.b_body_T + 1e-8
        self._next += 1.0
        return True


#: the Unix time of the first record of `good_tlog`
WALL0 = 1_750_000_000.0


def good_tlog(n=30) -> bytes:
    """An intact tlog of `n` magnetometer samples (HIGHRES_IMU), 0.1 s apart."""
    p = mavlink.MAVLink(None, srcSystem=FSW_SYSID, srcComponent=FSW_COMPID)
    out = b""
    for k in range(n):
        msg = mavlink.MAVLink_highres_imu_message(k * 100_000, 0, 0, 0, 0, 0, 0, 0.3, 0.1, -0.2, 0, 0, 0, 0, 0x1C0)
        msg.pack(p)
        p.seq = (p.seq + 1) % 256
        out += tlog_record(msg, WALL0 + 0.1 * k)
    return out


def tiers(prop, *strategies, **kw_strategies):
    """A property (a function of the drawn values) as its two tests: the fast one, with the loaded
    hypothesis profile (conftest.py: 200 examples, or 10,000 with HYPOTHESIS_PROFILE=fuzz), and the
    slow tier's, marked ``slow``, with the ``fuzz`` profile (10,000 examples)::

        test_reader, test_reader_fuzz = tiers(reader_property, inputs())
    """
    import pytest
    from hypothesis import given, settings

    fast = given(*strategies, **kw_strategies)(prop)
    slow = settings(settings.get_profile("fuzz"))(given(*strategies, **kw_strategies)(prop))
    return fast, pytest.mark.slow(slow)


def circular_tle(altitude_km=485.0, inclination_deg=97.5, epoch="26120.50000000", raan_deg=30.0, satnum="99999"):
    """A TLE of a near-circular orbit (e = 0.0001) at `altitude_km` above the WGS-72 equatorial radius,
    epoch `epoch` (YYDDD.DDDDDDDD), checksums right."""
    import math

    from fsw.estimation.tle import checksum
    a_km = 6378.135 + altitude_km
    rev_per_day = math.sqrt(398600.8 / a_km ** 3) * 86400.0 / (2 * math.pi)
    l1 = f"1 {satnum}U 26001A   {epoch}  .00000000  00000-0  00000-0 0  999"
    l2 = f"2 {satnum} {inclination_deg:8.4f} {raan_deg:8.4f} 0001000   0.0000   0.0000 {rev_per_day:11.8f}    1"
    return tuple(line + str(checksum(line + "0")) for line in (l1, l2))


def tle_epoch_field(dt):
    """A TLE's epoch field (YYDDD.DDDDDDDD) of the aware datetime `dt`."""
    from datetime import datetime, timezone

    start = datetime(dt.year, 1, 1, tzinfo=timezone.utc)
    return f"{dt.year % 100:02d}{(dt - start).total_seconds() / 86400 + 1:012.8f}"


# --- the host-magnetics calibration's truth: a tumble along the simulator's orbit, a host ------------

#: the orbit (altitude m, inclination °) and the field's epoch of the calibration tests
MAGCAL_ORBIT = (485e3, 97.5)
MAGCAL_EPOCH = 2025.5
MAGCAL_PERIOD_S = 2 * np.pi * np.sqrt((6378137.0 + MAGCAL_ORBIT[0]) ** 3 / 3.986004418e14)


@functools.lru_cache(maxsize=None)
def magcal_orbit(rate_hz: float = 1.0):
    """(t, B_ECI truth (hil.field: IGRF-14 to degree 13), |B| of the flight software's model (degree 8))
    over one orbit."""
    from fsw.estimation import field_motion as fm
    from fsw.estimation.onboard_field import flight_field
    from hil.field import FieldAlongOrbit, IgrfField
    from hil.orbit import CircularOrbit

    t = np.arange(0.0, MAGCAL_PERIOD_S, 1.0 / rate_hz)
    b_eci = FieldAlongOrbit(CircularOrbit(*MAGCAL_ORBIT), IgrfField(MAGCAL_EPOCH)).b_eci_T(t)
    model = flight_field(fm.CircularOrbitModel(*MAGCAL_ORBIT), MAGCAL_EPOCH)
    return t, b_eci, np.linalg.norm(model.b_eci_T(t), axis=1)


@functools.lru_cache(maxsize=None)
def magcal_tumble(seed: int) -> np.ndarray:
    """B in body axes along a torque-free tumble (2–5 °/s) of an asymmetric body (hil.dynamics), one orbit
    at 1 Hz."""
    from hil.dynamics import RigidBody

    t, b_eci, _ = magcal_orbit()
    rng = np.random.default_rng(1000 + seed)
    w = rng.normal(size=3)
    body = RigidBody(np.diag([180.0, 220.0, 260.0]), rng.normal(size=4),
                     w / np.linalg.norm(w) * np.radians(rng.uniform(2.0, 5.0)))
    out = np.empty_like(b_eci)
    for k, tk in enumerate(t):
        while body.t_s < tk - 1e-9:
            body.step(min(2.0, tk - body.t_s), np.zeros(3))
        out[k] = body.dcm.T @ b_eci[k]
    return out


def magcal_host(seed: int):
    """(S symmetric, h [T]) of B_meas = S B_true + h: hard iron to ±50 µT, soft iron to 10 %."""
    rng = np.random.default_rng(seed)
    A = rng.uniform(-0.1, 0.1, (3, 3))
    return np.eye(3) + np.triu(A) + np.triu(A, 1).T, rng.uniform(-50e-6, 50e-6, 3)


# --- the flight side's assumptions, made true in the simulated world --------------------------------
#: why a test pins them (say it where the test does)
FLIGHT_ASSUMES = ("a calibrated magnetometer: the host's iron is calibrated on board over an orbit, "
                  "longer than this test")


def flight_assumptions(name_or_scenario="isoi"):
    """The scenario without host magnetism (the calibration on board takes an orbit to converge; a test of
    an estimator on its own terms over a shorter run pins this; see FLIGHT_ASSUMES). The field is the
    world's (IGRF-14 to degree 13), the box's its own (degree 8)."""
    import dataclasses

    from hil import scenario
    from hil.host_magnetics import HostMagnetics

    scn = name_or_scenario if isinstance(name_or_scenario, scenario.Scenario) else scenario.load(name_or_scenario)
    return dataclasses.replace(scn, host=HostMagnetics())


def flight_assumptions_file(tmp_path, name: str = "isoi") -> str:
    """The same as a TOML file (for tests that go through a command line's --scenario)."""
    from hil import scenario

    text = scenario.resolve(name).read_text(encoding="utf-8").split("\n[host]")[0]
    path = tmp_path / f"{name}_flight_assumptions.toml"
    path.write_text(text, encoding="utf-8")
    return str(path)


def deorbit_loop(link=None):
    """The amds_deorbit closed loop as SITL composes it, at 10 Hz, without the identification experiment
    (the kit-field tests): the `hil.sitl` box; `link` None: no link (`NullLink`)."""
    from fsw.config import RunConfig
    from hil import scenario as scenarios
    from hil import sitl

    return sitl.build(sitl.SitlConfig(RunConfig(rate_hz=10, buffer_frames=0), scenario=scenarios.load("amds_deorbit"),
                                      seed=0, max_step_s=0.1), link=link if link is not None else NullLink(),
                      run_id=0, ident=False)


def start_controller(kit, t_s: float) -> int:
    """MAV_CMD_DEBRIS_CONTROLLER on (param1 = 1) handed to the de-orbit kit's application: its MAV_RESULT."""
    from types import SimpleNamespace

    return kit.handle_command(SimpleNamespace(command=mavlink.MAV_CMD_DEBRIS_CONTROLLER, param1=1, param2=0,
                                              param3=0, param4=0, param5=0, param6=0, param7=0), t_s)


def box_frames(seconds: float, sysid: int = FSW_SYSID, compid: int = FSW_COMPID, wall0_us: int = 1_750_000_000_000_000,
               run_id: int = 0x1234, rate_hz: int = 10) -> list[tuple[int, bytes]]:
    """(receive time µs, frame) of what a box sends for `seconds`: numbered magnetometer samples, the BOER
    estimate and the simulator's truth of each at `rate_hz`, a heartbeat and three status messages (zeros)
    a second; receive times 40 µs after
    the sample (multiples of 4 µs, so that a tlog's time stamps keep them exactly)."""
    p = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    out = []

    def send(msg, t_us):
        out.append((t_us, bytes(msg.pack(p))))
        p.seq = (p.seq + 1) % 256

    period_us = 1_000_000 // rate_hz
    for k in range(round(seconds * rate_hz)):
        box_us, wall_us = k * period_us, wall0_us + k * period_us + 40
        if k % rate_hz == 0:
            send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID,
                                                   0, 0, mavlink.MAV_STATE_ACTIVE, 3), wall_us)
            for cls in (mavlink.MAVLink_sys_status_message, mavlink.MAVLink_debris_mag_status_message,
                        mavlink.MAVLink_attitude_quaternion_message):
                send(cls(*[[0] * n if n else 0 for n in cls.array_lengths]), wall_us)
        b = [0.3 * math.cos(0.01 * k), 0.3 * math.sin(0.01 * k), -0.2]
        send(mavlink.MAVLink_debris_mag_sample_message(box_us, k, run_id, b, 0), wall_us)
        send(mavlink.MAVLink_debris_rate_estimate_message(box_us, 0.1, 0.2, 0.3 + 1e-4 * k, 0.01, 0.01, 0.01,
                                                          mavlink.DEBRIS_RATE_METHOD_BOER, 0), wall_us)
        send(mavlink.MAVLink_debris_sim_state_message(box_us, 0.1, 0.2, 0.3, [1, 0, 0, 0], *b, 0.0, 0.01, 0.0),
             wall_us)
    return out


def pymavlink_with_debris(directory) -> Path:
    """A directory to put first on PYTHONPATH that holds pymavlink as installed (its files linked) with the
    project's bindings added as the dialect ``debris`` (dialects/v20/debris.py): what a user's own
    pymavlink looks like after ``cp fsw/telemetry/mavlink_debris.py <pymavlink>/dialects/v20/debris.py``
    (docs/ground.md), without touching the installed one."""
    import os
    import shutil

    import pymavlink

    src, root = Path(pymavlink.__file__).parent, Path(directory)
    dst = root / "pymavlink"
    (dst / "dialects" / "v20").mkdir(parents=True)
    for sub, skip in (("", {"dialects"}), ("dialects", {"v20"}), ("dialects/v20", set())):
        for entry in (src / sub).iterdir():
            if entry.name not in skip and entry.name != "__pycache__":
                os.symlink(entry, dst / sub / entry.name)
    shutil.copy(Path(__file__).resolve().parents[1] / "fsw/telemetry/mavlink_debris.py",
                dst / "dialects/v20/debris.py")
    return root


def accuracy_record(mode: str, body: str, dt_s: float, sigma_uT: float, run_index: int, seed: int = 2024,
                    world: str = "dipole", whole: bool = False):
    """The scored record of run `run_index` of bench.accuracy's row (mode, body, dt_s, sigma_uT) in `world`, seeded
    as the benchmark seeds it: t, B, true ω, true B, σ_B (with the chip's noise), the field along the orbit;
    `whole`: the onboard filters' warm-up before the record too."""
    from bench import accuracy as acc
    from ground import smoother as sm
    row = acc.Row(mode, body, dt_s, sigma_uT, world)
    run = acc.simulate(mode, body, dt_s, sigma_uT * 1e-6, np.random.default_rng(acc.row_seed(row, seed) + [run_index]),
                       world=world)
    rec = slice(None) if whole else run.record
    t = run.t_s[rec]
    return (t, run.b_T[rec], run.w_true_radps[rec], run.b_true_T[rec], math.hypot(sigma_uT * 1e-6, acc.CHIP_NOISE_T),
            sm.tabulated(run.field, t))
