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
[field]    model = "igrf14-dipole", epoch_year
[sensor]   sample_rate_hz, bandwidth_hz (100/200/400/800), noise_uT, bridge_offset_uT
[[torque]] start_s, duration_s, moment_Nm   (known applied moment, body axes, about the centre of mass)
[deorbit]  optional, the de-orbit kit's closed loop (hil.deorbit_sim): see DeorbitSpec
```
"""
from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

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
    "field": {"model": str, "epoch_year": float},
    "sensor": {"sample_rate_hz": float, "bandwidth_hz": int, "noise_uT": float, "bridge_offset_uT": list},
}
_TOP = {"name", "description", "source", "torque", "deorbit", *_SCHEMA}
_BANDWIDTHS_HZ = (100, 200, 400, 800)
_FIELD_MODELS = ("igrf14-dipole",)


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
            if k not in keys:
                fail(f"{name}.{k}", f"unknown key (expected {sorted(keys)})")
        for k, typ in keys.items():
            if k not in table:
                fail(f"{name}.{k}", "missing")
            v = table[k]
            if typ is float and isinstance(v, int) and not isinstance(v, bool):
                try:
                    v = float(v)
                except OverflowError:
                    fail(f"{name}.{k}", f"must be finite (an integer of {len(str(abs(v)))} digits)")
            if not isinstance(v, typ):
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
        table = doc["deorbit"]
        if not isinstance(table, dict):
            fail("[deorbit]", "must be a table")
        kw = {}
        for k, v in table.items():
            if k not in DeorbitSpec.__dataclass_fields__:
                fail(f"deorbit.{k}", f"unknown key (expected {sorted(DeorbitSpec.__dataclass_fields__)})")
            vector = isinstance(getattr(DeorbitSpec, k), tuple)
            a = _numbers(v, (3,) if vector else ())
            if a is None:
                fail(f"deorbit.{k}", ("expected 3 finite numbers" if vector else "expected a finite number")
                     + f" (not strings), got {v!r}")
            kw[k] = tuple(float(x) for x in a) if vector else float(a)
        deorbit = DeorbitSpec(**kw)
        for k in ("sail_area_m2", "drag_coefficient", "density_kgm3", "density_scale_height_km",
                  "dipole_Am2", "duration_s"):
            if not getattr(deorbit, k) > 0:
                fail(f"deorbit.{k}", "must be > 0")
        if not 0 <= deorbit.settle_s < deorbit.duration_s:
            fail("deorbit.settle_s", "must be in [0, duration_s)")

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
        torques=tuple(pulses), deorbit=deorbit,
    )
