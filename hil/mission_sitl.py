"""SITL side of the mission (`fsw.deorbit.mission`): the identification experiment's magnets wired to the
de-orbit kit (`fsw.deorbit.mission.KitMagnets`), the box's guess of the tensor from the scenario's
[mission] table. The flown rate filter is handed to the mission by `hil.sitl.build` once the flight
software exists.
"""
from __future__ import annotations

import numpy as np

from fsw.deorbit.kit import DeorbitKit
from fsw.deorbit.mission import KitMagnets, Mission
from fsw.ident import IdentExperiment

from .scenario import Scenario


def build_mission(scn: Scenario, onboard: list, **options) -> Mission:
    """The mission over the kit and the experiment among the applications `onboard` (both needed);
    `options`: `fsw.deorbit.mission.Mission`'s keywords (config, detumble, on_phase)."""
    kit = next((a for a in onboard if isinstance(a, DeorbitKit)), None)
    ident = next((a for a in onboard if isinstance(a, IdentExperiment)), None)
    if kit is None or ident is None:
        raise ValueError("the mission needs the de-orbit kit and the identification experiment")
    guess = np.asarray(scn.mission.inertia_guess_kgm2, float)
    ident.magnets = KitMagnets(kit)
    ident.cfg.inertia_guess_kgm2 = float(np.mean(guess))  # the fit's start and weak prior: the box's guess
    return Mission(kit, ident, inertia_guess_kgm2=tuple(guess), **options)
