"""The spacecraft's drag: mass, areas, C_D, and the area the flow sees in each attitude mode.

- tumbling: a random tumble, every attitude equally likely. The mean projected area of a convex body
  is a quarter of its surface (Cauchy); a flat plate of area A (two faces, 2A of surface) shows A/2.
  The sail shows A/2; the body shows its midsection `body_m2` (the paper gives only that), or a
  quarter of its surface when `body_surface_m2` is given. `tumble_sail_fraction` (default 1/2) is the
  share of the sail shown on average: other values are for what-ifs (lapkhanov2019's tumbling times
  imply about 3/4; `ground.lifetime.paper`).
- stabilised: the sail held broadside to the flow: A · cos(yaw error) · cos(pitch error) (0 by default;
  `from_deorbit_json` takes the largest errors after convergence of a `python -m bench.deorbit --json`
  run, whose JSON holds those errors but no projected-area statistics: a lower bound on the area), plus
  the body's midsection.
- passive: the kit off. The sail is weathercock-stable (centre of pressure 0.12 m behind the centre of
  mass, docs/deorbit.md) but nothing damps it: it swings about broadside in yaw and pitch. With
  sinusoidal swings of amplitude θ0 in both, independent, it shows A · J0(θ0)² on average (⟨cos(θ0 sin
  ωt)⟩ = J0(θ0)); θ0 = 1 rad by default, the swing `bench.deorbit`'s craft keeps from 60°/45° without
  control. Plus the body's midsection.

C_D = 2.2 by default (the usual free-molecular value for a compact satellite), the same for all modes.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass

MODES = ("tumbling", "stabilised", "passive")


class CraftError(ValueError):
    """A mass, area or coefficient that makes no sense; the message names it."""


@dataclass(frozen=True)
class Craft:
    mass_kg: float
    sail_m2: float
    body_m2: float
    cd: float = 2.2
    body_surface_m2: float | None = None
    pointing_cos: float = 1.0            # cos(yaw err) · cos(pitch err) when stabilised
    tumble_sail_fraction: float = 0.5    # the share of the sail a tumbling craft shows on average
    passive_swing_rad: float = 1.0       # amplitude of the undamped yaw and pitch swings, kit off

    def check(self) -> "Craft":
        for name, v, zero_ok in (("mass", self.mass_kg, False), ("sail area", self.sail_m2, True),
                                 ("body area", self.body_m2, True), ("drag coefficient", self.cd, False)):
            if not math.isfinite(v) or v < 0 or (v == 0 and not zero_ok):
                raise CraftError(f"{name} must be {'≥ 0' if zero_ok else '> 0'}, got {v:g}")
        if self.body_surface_m2 is not None and not (math.isfinite(self.body_surface_m2) and self.body_surface_m2 > 0):
            raise CraftError(f"body surface must be > 0, got {self.body_surface_m2:g}")
        if not (0.0 <= self.pointing_cos <= 1.0):
            raise CraftError(f"pointing cosine must be within 0-1, got {self.pointing_cos:g}")
        if not (0.0 <= self.tumble_sail_fraction <= 1.0):
            raise CraftError(f"tumbling sail fraction must be within 0-1, got {self.tumble_sail_fraction:g}")
        if not (math.isfinite(self.passive_swing_rad) and 0.0 <= self.passive_swing_rad <= math.pi / 2):
            raise CraftError(f"passive swing must be within 0-90°, got {math.degrees(self.passive_swing_rad):g}°")
        if self.sail_m2 + self.body_m2 <= 0:
            raise CraftError("sail and body areas are both 0: nothing for the drag to act on")
        return self

    def area_m2(self, mode: str) -> float:
        """The mean area the flow sees in `mode` (module docstring)."""
        if mode == "tumbling":
            body = self.body_m2 if self.body_surface_m2 is None else self.body_surface_m2 / 4
            return self.sail_m2 * self.tumble_sail_fraction + body
        if mode == "stabilised":
            return self.sail_m2 * self.pointing_cos + self.body_m2
        if mode == "passive":
            from scipy.special import j0
            return self.sail_m2 * float(j0(self.passive_swing_rad)) ** 2 + self.body_m2
        raise CraftError(f"unknown attitude mode {mode!r}: one of {', '.join(MODES)}")

    def ballistic_m2kg(self, mode: str) -> float:
        """B = C_D A / m (m²/kg)."""
        return self.cd * self.area_m2(mode) / self.mass_kg


def pointing_cos_from_deorbit_json(path: str) -> float:
    """cos(yaw_err_max_rad) · cos(pitch_err_max_rad) of a `python -m bench.deorbit --json` file."""
    try:
        with open(path, encoding="utf-8") as f:
            d = json.load(f)
        yaw, pitch = float(d["yaw_err_max_rad"]), float(d["pitch_err_max_rad"])
    except OSError as e:
        raise CraftError(f"{path}: {e.strerror or e}") from None
    except (ValueError, KeyError, TypeError) as e:
        raise CraftError(f"{path}: not a bench.deorbit JSON with yaw_err_max_rad and pitch_err_max_rad ({e})") from None
    if not (math.isfinite(yaw) and math.isfinite(pitch)):
        raise CraftError(f"{path}: the run's pointing errors are not finite (it did not converge)")
    return max(math.cos(yaw), 0.0) * max(math.cos(pitch), 0.0)
