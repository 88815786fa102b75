"""SITL scenarios: TOML files describing the debris, its orbit, the sensor and the applied torques.

A scenario is named (`isoi`, `aist2d`, `amds`: the files in `hil/scenarios/`) or given as a path.
Units are in the key names; values are converted to SI when loaded. Unknown keys are an error, so a
typo never silently falls back to a default; so is a value of the wrong kind: a number written as a
string (``"10"``), a boolean where a number belongs, a scalar where a table or an array of tables is
expected. Every error is a :class:`ScenarioError` naming the file and the key.

```toml
name = "isoi"
description = "..."
[body]     mass_kg, inertia_kgm2 (3x3, symmetric, about the centre of mass, body = sensor axes)
[initial]  omega_dps (body rate), attitude_rpy_deg (roll, pitch, yaw; body to ECI, ZYX sequence)
[orbit]    altitude_km, inclination_deg, raan_deg, arg_lat0_deg (circular orbit)
           optional: tle = ["1 ...", "2 ..."] and utc0 = 2025-07-01T00:00:00Z (t = 0): the truth flies the
           TLE through SGP4 (hil.orbit.TleOrbit, TEME) instead of the circular orbit, which stays the
           nominal description; box_tle = [...]: an older TLE, what the box is given (Scenario.box_tle)
[field]    model = "igrf14" (default: IGRF-14, `degree` 1..13, default 13) or "igrf14-dipole", epoch_year
[host]     optional, the host's magnetism (hil.host_magnetics): hard_iron_uT, soft_iron,
           hard_iron_drift_uT, drift_period_s, drift_phase_deg
[clock]    optional, the box's clock against true time (hil.box_clock): offset_s, drift_ppm
[sensor]   sample_rate_hz, bandwidth_hz (100/200/400/800), noise_uT, bridge_offset_uT
[[torque]] start_s, duration_s, moment_Nm   (known applied moment, body axes, about the centre of mass)
[deorbit]  optional, the de-orbit kit's closed loop (hil.deorbit_sim): see DeorbitSpec
[mission]  optional, with [deorbit]: the whole mission (fsw.deorbit.mission): see MissionSpec
```
"""
from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from .box_clock import BoxClock
from .host_magnetics import HostMagnetics

SCENARIO_DIR = Path(__file__).with_name("scenarios")
DEFAULT_SCENARIO = "isoi"


class ScenarioError(ValueError):
    """A scenario file that cannot be used; the message names the file and the key."""


@dataclass(frozen=True)
class TorquePulse:
    start_s: float
    duration_s: float
    moment_Nm: np.ndarray

    def active(self, t_s: float) -> bool:
        return self.start_s <= t_s < self.start_s + self.duration_s


@dataclass(frozen=True)
class DeorbitSpec:
    """The optional [deorbit] table: the AMDS spacecraft of lapkhanov2019 with its sail and magnets.

    Every key is optional (defaults: the paper's numbers). `initial_ypr_deg` (yaw, pitch, roll) and
    `initial_rate_dps` (body rate relative to the orbital frame) give the initial attitude w.r.t. the
    orbital frame (x along the velocity, z to nadir; ZYX) and replace [initial] in the de-orbit
    simulator. Density: ρ = density_kgm3 · exp(−(h − density_ref_alt_km) / density_scale_height_km).
    `settle_s`: yaw and pitch are scored from this time on.
    """

    initial_ypr_deg: tuple[float, float, float] = (60.0, 45.0, 0.0)
    initial_rate_dps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    sail_area_m2: float = 5.0
    body_area_m2: float = 0.58
    drag_coefficient: float = 2.2
    cp_offset_m: tuple[float, float, float] = (-0.12, 0.0, 0.0)
    density_kgm3: float = 1.454e-13
    density_ref_alt_km: float = 600.0
    density_scale_height_km: float = 71.835
    dipole_Am2: float = 15.0
    duration_s: float = 10800.0
    settle_s: float = 3600.0
    #: where the magnets sit relative to the magnetometer, body axes (hil.kit_field)
    pitch_magnet_position_m: tuple[float, float, float] = (0.0, 0.3, 0.0)
    yaw_magnet_position_m: tuple[float, float, float] = (0.0, 0.0, -0.3)
    #: the fraction of a magnet's field a closed capsule lets out
    capsule_leakage: float = 0.015


@dataclass(frozen=True)
class MissionSpec:
    """The optional [mission] table (with [deorbit]): the mission from a tumble (`fsw.deorbit.mission`).

    `inertia_guess_kgm2`: the diagonal the box is told (a rough guess; the truth is [body]'s);
    `duration_s`: how long SITL's benchmark runs the mission. The tumble is [deorbit]'s
    `initial_rate_dps` (relative to the orbital frame)."""

    inertia_guess_kgm2: tuple[float, float, float] = (17.995, 20.711, 15.269)
    duration_s: float = 30000.0


@dataclass(frozen=True)
class Scenario:
    name: str
    description: str
    source: str
    path: Path
    mass_kg: float
    inertia_kgm2: np.ndarray
    omega0_radps: np.ndarray
    attitude_rpy_deg: np.ndarray
    altitude_m: float
    inclination_deg: float
    raan_deg: float
    arg_lat0_deg: float
    field_model: str
    epoch_year: float
    sample_rate_hz: float
    bandwidth_hz: int
    noise_T: float
    bridge_offset_T: np.ndarray
    torques: tuple[TorquePulse, ...] = field(default_factory=tuple)
    deorbit: DeorbitSpec | None = None
    mission: MissionSpec | None = None
    #: IGRF degree of the "igrf14" field model
    field_degree: int = 13
    #: the truth's TLE (two lines) and the UTC of t = 0 (naive, UTC); None: the circular orbit
    tle: tuple[str, str] | None = None
    utc0: datetime | None = None
    #: the TLE the box is given (may be older than the truth's); None: the truth's
    box_tle: tuple[str, str] | None = None
    host: HostMagnetics = field(default_factory=HostMagnetics)
    clock: BoxClock = field(default_factory=BoxClock)

    def moment_Nm(self, t_s: float, out: np.ndarray | None = None) -> np.ndarray:
        """Applied moment at time t (sum of the active pulses), body axes."""
        m = out if out is not None else np.zeros(3)
        m[:] = 0.0
        for p in self.torques:
            if p.active(t_s):
                m += p.moment_Nm
        return m


_SCHEMA: dict[str, dict[str, type | tuple]] = {
    "body": {"mass_kg": float, "inertia_kgm2": list},
    "initial": {"omega_dps": list, "attitude_rpy_deg": list},
    "orbit": {"altitude_km": float, "inclination_deg": float, "raan_deg": float, "arg_lat0_deg": float},
    "field": {"model": str, "epoch_year": float, "degree": int},
    "sensor": {"sample_rate_hz": float, "bandwidth_hz": int, "noise_uT": float, "bridge_offset_uT": list},
}
_OPTIONAL = {("field", "model"): "igrf14", ("field", "degree"): 13}
_TOP = {"name", "description", "source", "torque", "deorbit", "mission", "host", "clock", *_SCHEMA}
_BANDWIDTHS_HZ = (100, 200, 400, 800)
_FIELD_MODELS = ("igrf14", "igrf14-dipole")
_ORBIT_TLE_KEYS = ("tle", "utc0", "box_tle")
_HOST_KEYS = {"hard_iron_uT": (3,), "soft_iron": (3, 3), "hard_iron_drift_uT": (3,), "drift_period_s": (),
              "drift_phase_deg": ()}
_CLOCK_KEYS = ("offset_s", "drift_ppm")


def tle_checksum_ok(line: str) -> bool:
    """The TLE line's last digit is the sum of its digits, with 1 per minus sign, modulo 10."""
    if len(line) != 69 or not line[68].isdigit():
        return False
    total = sum(int(c) if c.isdigit() else (1 if c == "-" else 0) for c in line[:68])
    return total % 10 == int(line[68])


def scenario_names() -> list[str]:
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.toml"))


def resolve(name_or_path: str) -> Path:
    p = Path(name_or_path)
    if p.suffix == ".toml" or p.exists():
        if not p.is_file():
            raise ScenarioError(f"{p}: no such scenario file")
        return p
    p = SCENARIO_DIR / f"{name_or_path}.toml"
    if not p.is_file():
        raise ScenarioError(f"unknown scenario {name_or_path!r}; shipped: {', '.join(scenario_names())}")
    return p


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _number_table(table, name: str, spec, fail, *, positive: bool = False) -> dict:
    """The keyword arguments of dataclass `spec` from the scenario's table [name]: every key one of its
    fields, a number (or 3 numbers where the field's default is a tuple), finite (and > 0 if `positive`)."""
    if not isinstance(table, dict):
        fail(f"[{name}]", "must be a table")
    kw = {}
    for k, v in table.items():
        if k not in spec.__dataclass_fields__:
            fail(f"{name}.{k}", f"unknown key (expected {sorted(spec.__dataclass_fields__)})")
        vector = isinstance(getattr(spec, k), tuple)
        a = _numbers(v, (3,) if vector else ())
        if a is None or (positive and not np.all(a > 0)):
            what = ("3 finite numbers" if vector else "a finite number") + (" > 0" if positive else " (not strings)")
            fail(f"{name}.{k}", f"expected {what}, got {v!r}")
        kw[k] = tuple(float(x) for x in a) if vector else float(a)
    return kw


def _numbers(v, shape: tuple) -> np.ndarray | None:
    """`v` as a float array of `shape` if it is nested lists of finite numbers (not strings, not
    booleans) of that shape; None otherwise."""
    def flat(x):
        if isinstance(x, list):
            for y in x:
                yield from flat(y)
        else:
            yield x

    if shape and not isinstance(v, list):
        return None
    items = list(flat(v)) if shape else [v]
    if not all(map(_is_number, items)):
        return None
    try:
        a = np.array(v, dtype=float)
    except (TypeError, ValueError, OverflowError):  # ragged, or an integer no float holds
        return None
    return a if a.shape == shape and np.all(np.isfinite(a)) else None


def load(name_or_path: str = DEFAULT_SCENARIO) -> Scenario:
    path = resolve(name_or_path)
    try:
        text = path.read_text(encoding="utf-8")  # TOML is UTF-8, whatever the locale
    except (OSError, UnicodeDecodeError) as e:
        raise ScenarioError(f"{path}: cannot read: {getattr(e, 'strerror', None) or e}") from None
    try:
        doc = tomllib.loads(text)
    except ValueError as e:  # TOMLDecodeError, or an integer of more than 4300 digits
        raise ScenarioError(f"{path}: not valid TOML: {e}") from None
    except RecursionError:
        raise ScenarioError(f"{path}: not valid TOML: arrays or tables nested too deeply") from None

    def fail(key: str, why: str):
        raise ScenarioError(f"{path}: {key}: {why}")

    for key in doc:
        if key not in _TOP:
            fail(key, f"unknown key (expected one of {sorted(_TOP)})")
    for key in ("name", "description", "source"):
        if key in doc and not isinstance(doc[key], str):
            fail(key, f"expected a string, got {type(doc[key]).__name__}")
    sec: dict[str, dict] = {}
    for name, keys in _SCHEMA.items():
        table = doc.get(name)
        if table is None:
            fail(f"[{name}]", "missing table")
        if not isinstance(table, dict):
            fail(f"[{name}]", f"must be a table, got {type(table).__name__}")
        for k in table:
            if k not in keys and not (name == "orbit" and k in _ORBIT_TLE_KEYS):
                fail(f"{name}.{k}", f"unknown key (expected {sorted(keys)})")
        table = dict(table)
        for k, typ in keys.items():
            if k not in table:
                if (name, k) not in _OPTIONAL:
                    fail(f"{name}.{k}", "missing")
                table[k] = _OPTIONAL[name, k]
            v = table[k]
            if typ is float and isinstance(v, int) and not isinstance(v, bool):
                try:
                    v = float(v)
                except OverflowError:
                    fail(f"{name}.{k}", f"must be finite (an integer of {len(str(abs(v)))} digits)")
            if not isinstance(v, typ) or (typ is int and isinstance(v, bool)):
                fail(f"{name}.{k}", f"expected {typ.__name__}, got {type(v).__name__}")
            if typ is float and not np.isfinite(v):
                fail(f"{name}.{k}", "must be finite")
        sec[name] = table

    def vec(name: str, k: str, shape: tuple) -> np.ndarray:
        a = _numbers(sec[name][k], shape)
        if a is None:
            fail(f"{name}.{k}", f"expected finite numbers (not strings) of shape {shape}, got {sec[name][k]!r}")
        return a

    J = vec("body", "inertia_kgm2", (3, 3))
    if not np.allclose(J, J.T, rtol=0, atol=1e-12 * np.abs(J).max()):
        fail("body.inertia_kgm2", "must be symmetric")
    ev = np.linalg.eigvalsh(J)
    if ev[0] <= 0:
        fail("body.inertia_kgm2", f"must be positive definite (eigenvalues {ev})")
    if ev[0] / ev[2] + ev[1] / ev[2] < 1 - 1e-9:  # (divided: no overflow near the float limit)
        fail("body.inertia_kgm2", f"principal moments {ev} violate the triangle inequality")
    mass = float(sec["body"]["mass_kg"])
    if mass <= 0:
        fail("body.mass_kg", "must be > 0")
    orbit = sec["orbit"]
    if not 100.0 <= orbit["altitude_km"] <= 50_000.0:
        fail("orbit.altitude_km", "must be within 100 .. 50000 km")
    sensor = sec["sensor"]
    if sensor["bandwidth_hz"] not in _BANDWIDTHS_HZ:
        fail("sensor.bandwidth_hz", f"must be one of {_BANDWIDTHS_HZ}")
    if not 0 < sensor["sample_rate_hz"] <= 1000.0:
        fail("sensor.sample_rate_hz", "must be in (0, 1000] Hz (the MMC5983MA's ceiling)")
    if sensor["noise_uT"] < 0:
        fail("sensor.noise_uT", "must be >= 0")
    if sec["field"]["model"] not in _FIELD_MODELS:
        fail("field.model", f"must be one of {_FIELD_MODELS}")
    if not 1 <= sec["field"]["degree"] <= 13:
        fail("field.degree", "must be within 1 .. 13")
    from .field import make_field
    try:  # the field model's validity (epoch)
        make_field(sec["field"]["model"], float(sec["field"]["epoch_year"]), sec["field"]["degree"])
    except ValueError as e:
        fail("field.epoch_year", str(e))
    tle, utc0, box_tle = _orbit_tle(orbit, fail)
    host = _host(doc.get("host"), fail)
    clock = _clock(doc.get("clock"), fail)

    pulses = []
    torques = doc.get("torque", [])
    if not isinstance(torques, list):
        fail("torque", f"must be an array of tables ([[torque]] sections), got {type(torques).__name__}")
    for i, p in enumerate(torques):
        where = f"torque[{i}]"
        if not isinstance(p, dict) or set(p) != {"start_s", "duration_s", "moment_Nm"}:
            fail(where, "needs exactly start_s, duration_s, moment_Nm")
        m = _numbers(p["moment_Nm"], (3,))
        if m is None:
            fail(f"{where}.moment_Nm", f"expected 3 finite numbers (not strings), got {p['moment_Nm']!r}")
        for k in ("start_s", "duration_s"):
            if _numbers(p[k], ()) is None:
                fail(f"{where}.{k}", f"expected a finite number (not a string), got {p[k]!r}")
        if not (p["duration_s"] > 0 and p["start_s"] >= 0):
            fail(where, "start_s must be >= 0 and duration_s > 0")
        pulses.append(TorquePulse(float(p["start_s"]), float(p["duration_s"]), m))

    deorbit = None
    if "deorbit" in doc:
        deorbit = DeorbitSpec(**_number_table(doc["deorbit"], "deorbit", DeorbitSpec, fail))
        for k in ("sail_area_m2", "drag_coefficient", "density_kgm3", "density_scale_height_km",
                  "dipole_Am2", "duration_s"):
            if not getattr(deorbit, k) > 0:
                fail(f"deorbit.{k}", "must be > 0")
        if not 0 <= deorbit.settle_s < deorbit.duration_s:
            fail("deorbit.settle_s", "must be in [0, duration_s)")
        if not 0 <= deorbit.capsule_leakage <= 1:
            fail("deorbit.capsule_leakage", "must be within [0, 1]")
        for k in ("pitch_magnet_position_m", "yaw_magnet_position_m"):
            if np.linalg.norm(getattr(deorbit, k)) < 0.01:
                fail(f"deorbit.{k}", "a magnet must sit at least 1 cm from the magnetometer")

    mission = None
    if "mission" in doc:
        if isinstance(doc["mission"], dict) and deorbit is None:
            fail("[mission]", "needs a [deorbit] table (the kit and the sail)")
        mission = MissionSpec(**_number_table(doc["mission"], "mission", MissionSpec, fail, positive=True))

    return Scenario(
        name=str(doc.get("name", path.stem)), description=str(doc.get("description", "")),
        source=str(doc.get("source", "")), path=path, mass_kg=mass, inertia_kgm2=J,
        omega0_radps=np.radians(vec("initial", "omega_dps", (3,))),
        attitude_rpy_deg=vec("initial", "attitude_rpy_deg", (3,)),
        altitude_m=orbit["altitude_km"] * 1e3, inclination_deg=orbit["inclination_deg"],
        raan_deg=orbit["raan_deg"], arg_lat0_deg=orbit["arg_lat0_deg"],
        field_model=sec["field"]["model"], epoch_year=sec["field"]["epoch_year"],
        sample_rate_hz=sensor["sample_rate_hz"], bandwidth_hz=sensor["bandwidth_hz"],
        noise_T=sensor["noise_uT"] * 1e-6, bridge_offset_T=vec("sensor", "bridge_offset_uT", (3,)) * 1e-6,
        torques=tuple(pulses), deorbit=deorbit, mission=mission, field_degree=sec["field"]["degree"],
        tle=tle, utc0=utc0, box_tle=box_tle, host=host, clock=clock,
    )


def _orbit_tle(orbit: dict, fail) -> tuple[tuple[str, str] | None, datetime | None, tuple[str, str] | None]:
    """[orbit] tle, utc0, box_tle: checked (two lines, checksums, SGP4 can propagate the truth's to utc0)."""
    def lines(k):
        v = orbit.get(k)
        if v is None:
            return None
        if not (isinstance(v, list) and len(v) == 2 and all(isinstance(x, str) for x in v)):
            fail(f"orbit.{k}", "expected two strings, the TLE's lines 1 and 2")
        v = tuple(x.rstrip() for x in v)
        for i, line in enumerate(v, 1):
            if not line.startswith(f"{i} "):
                fail(f"orbit.{k}", f"line {i} must start with '{i} '")
            if not tle_checksum_ok(line):
                fail(f"orbit.{k}", f"line {i}: bad checksum or not 69 characters")
        return v

    tle, box_tle = lines("tle"), lines("box_tle")
    utc0 = orbit.get("utc0")
    if (tle is None) != (utc0 is None):
        fail("orbit.utc0" if tle else "orbit.tle", "tle and utc0 go together (utc0: the UTC of t = 0)")
    if box_tle is not None and tle is None:
        fail("orbit.box_tle", "needs the truth's tle and utc0")
    if utc0 is None:
        return None, None, None
    if not isinstance(utc0, datetime):
        fail("orbit.utc0", f"expected a TOML date-time (2025-07-01T00:00:00Z), got {utc0!r}")
    if utc0.tzinfo is not None:
        utc0 = utc0.astimezone(timezone.utc).replace(tzinfo=None)
    from .orbit import TleOrbit
    for k, v in (("tle", tle), ("box_tle", box_tle)):
        if v is None:
            continue
        try:
            TleOrbit(*v, utc0)
        except Exception as e:  # sgp4 raises ValueError, or worse for a malformed line
            fail(f"orbit.{k}", f"SGP4 cannot use it at utc0 {utc0}: {e}")
    return tle, utc0, box_tle


def _host(table, fail) -> HostMagnetics:
    if table is None:
        return HostMagnetics()
    if not isinstance(table, dict):
        fail("[host]", "must be a table")
    for k, v in table.items():
        if k not in _HOST_KEYS:
            fail(f"host.{k}", f"unknown key (expected {sorted(_HOST_KEYS)})")
        if _numbers(v, _HOST_KEYS[k]) is None:
            fail(f"host.{k}", f"expected finite numbers (not strings) of shape {_HOST_KEYS[k]}, got {v!r}")
    try:
        return HostMagnetics.from_table(table)
    except ValueError as e:
        fail("[host]", str(e))


def _clock(table, fail) -> BoxClock:
    if table is None:
        return BoxClock()
    if not isinstance(table, dict):
        fail("[clock]", "must be a table")
    for k, v in table.items():
        if k not in _CLOCK_KEYS:
            fail(f"clock.{k}", f"unknown key (expected {list(_CLOCK_KEYS)})")
        if _numbers(v, ()) is None:
            fail(f"clock.{k}", f"expected a finite number (not a string), got {v!r}")
    try:
        return BoxClock(float(table.get("offset_s", 0.0)), float(table.get("drift_ppm", 0.0)))
    except ValueError as e:
        fail("[clock]", str(e))
