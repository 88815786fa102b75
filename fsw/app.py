"""The contract of an onboard application: what the flight software needs to run it.

The flight software (`fsw.flight.FlightSoftware`) builds its task table from its applications: each
gets a task at its own rate with its own time budget, after the sensor and the estimators and before
the telemetry, and its ground commands go through the one command router. Like ArduPilot's backends
or F´'s components, an application never reaches into the flight software: it is given the latched
magnetometer sample and the telemetry, and it registers its commands.
"""
from __future__ import annotations

from typing import Protocol

import numpy as np

from .commands import CommandRouter
from .telemetry.telemetry import Telemetry


class Sample(Protocol):
    """The magnetometer sample accepted this tick (`FlightSoftware.sample`)."""

    t_s: float
    b_T: np.ndarray


class App(Protocol):
    """An onboard application."""

    #: the task's name in the table and in telemetry
    name: str
    #: how often its tick runs, Hz (capped at the loop rate)
    rate_hz: float
    #: the share of the loop period one tick may take (a longer one is counted as a task overrun)
    budget: float

    def register(self, commands: CommandRouter) -> None:
        """Register its ground commands."""

    def tick(self, now_s: float, sample: Sample | None) -> None:
        """One run of its task; `sample`: the magnetometer sample accepted since its last tick, or None."""

    def telemetry(self, now_s: float, tlm: Telemetry) -> None:
        """Send what is due (it keeps its own rates); called right after each tick."""

    # optional: register_params(params) — its parameters (`fsw.commands.ParamTable`);
    # message_handlers() -> {message type: handler(msg, now_s, authenticated)} — messages from the ground
    # beyond commands (e.g. SYSTEM_TIME), handed over by the uplink after its signature check
