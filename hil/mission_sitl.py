"""SITL side of the mission (`fsw.deorbit.mission`): the mission over the kit and the identification
experiment among the SITL's applications, with the box's guess of the tensor from the scenario's [mission]
table (`fsw.deorbit.mission.over_kit`, the composition the target uses too). The flown rate filter is
handed to the mission by `fsw.system.build_flight` once the flight software exists.
"""
from __future__ import annotations

from fsw.deorbit.kit import DeorbitKit
from fsw.deorbit.mission import Mission, over_kit
from fsw.ident import IdentExperiment

from .scenario import Scenario


def build_mission(scn: Scenario, onboard: list, **options) -> Mission:
    """The mission over the kit and the experiment among the applications `onboard` (both needed);
    `options`: `fsw.deorbit.mission.Mission`'s keywords (config, detumble, on_phase)."""
    kit = next((a for a in onboard if isinstance(a, DeorbitKit)), None)
    ident = next((a for a in onboard if isinstance(a, IdentExperiment)), None)
    if kit is None or ident is None:
        raise ValueError("the mission needs the de-orbit kit and the identification experiment")
    return over_kit(kit, ident, scn.mission.inertia_guess_kgm2, **options)
