"""The de-orbit kit's magnets as the magnetometer sees them.

Each magnet is a point dipole at ``position_m`` (body axes, from the magnetometer to the magnet's
centre). Its moment is the channel's (``hil.deorbit_kit.ChannelEmulator``): ``p`` along its home axis
turned by the stepper's rotor angle, scaled by its capsule's screening. A closed capsule leaks
``leakage`` of the field (1-2 % for a mu-metal can); an opening shutter lets out the rest in
proportion to its opening ``s``::

    m = (leakage + (1 − leakage) · s) · p · Rx(φ) a

and its field at the sensor (r from the dipole to the sensor, r̂ = r / |r|)::

    B = μ0 / (4π |r|³) · (3 (m·r̂) r̂ − m)

15 A·m² on its axis at 0.3 m gives 111 µT, across it 56 µT: two to five times the Earth's field. The
torque on the body still uses the unscreened dipole s·p·Rx(φ)a (``hil.environment``); the leakage only
reaches the sensor here.

Scenario keys (``[deorbit]``): ``pitch_magnet_position_m``, ``yaw_magnet_position_m``,
``capsule_leakage``.
"""
from __future__ import annotations

import numpy as np

from .field import MU0_NA2

__all__ = ["dipole_field_T", "KitFieldAtSensor"]


def dipole_field_T(m_Am2: np.ndarray, r_m: np.ndarray) -> np.ndarray:
    """Field [T] of a point dipole `m_Am2` at the displacement `r_m` from the dipole to the point."""
    r = np.asarray(r_m, dtype=float)
    m = np.asarray(m_Am2, dtype=float)
    d = float(np.linalg.norm(r))
    rh = r / d
    return MU0_NA2 / (4.0 * np.pi * d**3) * (3.0 * np.dot(m, rh) * rh - m)


class KitFieldAtSensor:
    """B at the magnetometer from the kit's magnets, from the emulated channels' state now."""

    def __init__(self, kit, positions_m, leakage: float = 0.015) -> None:
        if not 0.0 <= leakage <= 1.0:
            raise ValueError(f"capsule leakage must be within [0, 1], got {leakage!r}")
        self.kit = kit
        self.positions_m = [np.asarray(p, dtype=float) for p in positions_m]
        if len(self.positions_m) != len(kit.channels):
            raise ValueError("one magnet position per channel")
        for p in self.positions_m:
            if not (p.shape == (3,) and np.all(np.isfinite(p)) and np.linalg.norm(p) > 0.01):
                raise ValueError(f"a magnet must sit at least 1 cm from the sensor, got {p}")
        self.leakage = float(leakage)

    def moment_Am2(self, channel) -> np.ndarray:
        """The moment the sensor sees from one channel: its rotor's axis, screened by its capsule."""
        full = channel.dipole_Am2 * channel.axis_body()
        return (self.leakage + (1.0 - self.leakage) * channel.shutter) * full

    def b_body_T(self) -> np.ndarray:
        """Sum over the magnets of their field at the sensor, body axes [T]."""
        b = np.zeros(3)
        for ch, p in zip(self.kit.channels, self.positions_m):
            b += dipole_field_T(self.moment_Am2(ch), -p)
        return b
