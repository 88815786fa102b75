"""The mission in the SITL composition (`hil.sitl.build` on scenario amds_mission): the mission application
on the flight software with the experiment's magnets wired to the kit and the flown rate filter handed over,
its commands registered, its status and phase changes decoded on the ground from the link's bytes."""
import pytest

from fsw.config import RunConfig
from fsw.deorbit.mission import KitMagnets, Phase
from fsw.telemetry.dialect import mavlink
from ground.decode import Decoder
from hil import sitl
from support import Capture

pytestmark = pytest.mark.sitl


def test_the_mission_runs_in_sitl_and_the_ground_decodes_it():
    link = Capture()
    box = sitl.build(sitl.SitlConfig(RunConfig(rate_hz=5.0, buffer_frames=0, rate_filter="fixed"),
                                     scenario="amds_mission", seed=1, max_step_s=0.2), link=link, run_id=0)
    fsw = box.fsw
    mission, ident, kit = fsw.apps["mission"], fsw.apps["ident"], fsw.apps["deorbit"]
    assert isinstance(ident.magnets, KitMagnets) and ident.magnets.kit is kit
    assert mission.rates is fsw.estimators["kalman"]
    assert {mavlink.MAV_CMD_DEBRIS_MISSION_PHASE, mavlink.MAV_CMD_DEBRIS_MISSION_SAFE} <= set(fsw.commands.registered())
    t = box.t0_s
    for _ in range(150):                   # 30 s
        t += 0.2
        box.advance(t)
        fsw.tick(t)
    assert mission.phase is Phase.TUMBLING and mission.omega_radps is not None
    assert kit.attitude is None            # the controller's filter waits for the identified tensor...
    assert mission._attitude_template.provider is not None   # ...with the field the composition gave it
    dec = Decoder()
    for i, msg in enumerate(link.messages()):
        dec.handle(msg, 1000.0 + i * 1e-3)
    assert dec.mission["phase"] == "TUMBLING" and dec.mission["reason"] == "start"
    assert dec.mission["inertia_kgm2"] == pytest.approx((17.995, 20.711, 15.269), rel=1e-6)  # the box's guess
    assert 25.0 <= dec.mission["time_in_phase_s"] <= 30.0
    assert "mission: TUMBLING" in dec.summary_text()
