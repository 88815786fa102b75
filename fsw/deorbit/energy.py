"""Energy ledger of the de-orbit kit: per channel and per kind of motor.

Each motor draws 11.7 W while it moves (lapkhanov2019: two windings of 1.8 A at 3.25 V); the drivers
integrate power × time moving (`Capsule.energy_J`, `Stepper.energy_J`, homing included). The spring
that closes a capsule costs nothing. The paper's figures for 10,800 s: 45 openings × 2 s × 11.7 W =
1,053 J for the capsules, 60 turns × 1 s × 11.7 W = 702 J for the magnets, 1,755 J in all.
"""
from __future__ import annotations

from dataclasses import dataclass

CHANNEL_NAMES = ("pitch", "yaw")
PAPER_CAPSULES_J = 1053.0
PAPER_MAGNETS_J = 702.0
PAPER_TOTAL_J = PAPER_CAPSULES_J + PAPER_MAGNETS_J
PAPER_OPENINGS = {"pitch": 15, "yaw": 30}
"""Openings per channel in the paper: 15 for M_y (pitch channel), 30 for M_z (yaw channel)."""
PAPER_TURNS = {"pitch": 35, "yaw": 25}


@dataclass(frozen=True)
class ChannelEnergy:
    capsule_J: float
    magnet_J: float
    openings: int
    turns: int
    steps: int

    @property
    def total_J(self) -> float:
        return self.capsule_J + self.magnet_J


@dataclass(frozen=True)
class EnergyLedger:
    """A snapshot of the kit's energy use since start."""

    channels: tuple[ChannelEnergy, ChannelEnergy]

    @classmethod
    def of(cls, steppers, capsules) -> "EnergyLedger":
        return cls(tuple(ChannelEnergy(c.energy_J, s.energy_J, c.openings, s.turns, s.steps_total)
                         for s, c in zip(steppers, capsules)))

    @property
    def capsules_J(self) -> float:
        return sum(c.capsule_J for c in self.channels)

    @property
    def magnets_J(self) -> float:
        return sum(c.magnet_J for c in self.channels)

    @property
    def total_J(self) -> float:
        return self.capsules_J + self.magnets_J

    def as_dict(self) -> dict:
        """{"pitch": J, "yaw": J, "capsules": J, "magnets": J, "total": J} (the bench's `energy_J`)."""
        d = {name: c.total_J for name, c in zip(CHANNEL_NAMES, self.channels)}
        d.update(capsules=self.capsules_J, magnets=self.magnets_J, total=self.total_J)
        return d
