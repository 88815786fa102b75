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


def test_a_restart_of_the_flight_software_on_the_running_world_keeps_what_the_box_saved(tmp_path):
    """With a state directory (as on target) the box saves its host calibration; started again on the same
    world (`sim`) with a capsule left open by the old run, a new driver takes the chip from PROBE, the
    calibration comes back from the directory, the mission starts in TUMBLING again, and the capsule is
    closed by its spring rather than taken for a switch fault."""
    from bench.deorbit import hand_over_calibration
    from fsw.drivers.capsule import CapsuleState
    from fsw.drivers.mmc5983ma import MagState

    cfg = sitl.SitlConfig(RunConfig(rate_hz=5.0, buffer_frames=0, rate_filter="fixed", state_dir=str(tmp_path)),
                          scenario="amds_mission", seed=1, max_step_s=0.2)
    box = sitl.build(cfg, link=Capture(), run_id=0)
    hand_over_calibration(box.fsw.calibration, box.sim.host, seed=1)
    t = box.t0_s
    for _ in range(50):                    # 10 s
        t += 0.2
        box.advance(t)
        box.tick(t)
    seq = box.fsw.apps["deorbit"].sequencer
    assert seq.request_home(1, t).accepted
    while seq.channels[1].busy:            # homed
        t += 0.2
        box.advance(t)
        box.tick(t)
    assert seq.request_capsule(1, True, t).accepted
    for _ in range(6):                     # 1.2 s: the yaw capsule half-way open when the software stops
        t += 0.2
        box.advance(t)
        box.tick(t)
    assert 0.2 < box.sim.kit.channels[1].shutter < 1.0
    saved = box.fsw.calibration.snapshot()
    box.close()
    assert (tmp_path / "calibration.json").is_file()

    again = sitl.build(cfg, link=Capture(), run_id=0, sim=box.sim)
    assert again.sim is box.sim and again.driver is not box.driver and again.driver.state is MagState.PROBE
    assert again.state.restored.get("calibration") and any("calibration: restored" in n for n in again.flight.notes)
    restored = again.fsw.calibration.snapshot()
    assert restored["b_T"] == pytest.approx(saved["b_T"]) and restored["theta_uT"] == pytest.approx(saved["theta_uT"])
    mission, kit = again.fsw.apps["mission"], again.fsw.apps["deorbit"]
    for _ in range(25):                    # 5 s
        t += 0.2
        again.advance(t)
        again.tick(t)
    cap = kit.sequencer.channels[1].capsule
    assert cap.found_open == 1 and cap.fault == 0 and cap.state is CapsuleState.CLOSED
    assert again.sim.kit.channels[1].shutter == 0.0
    assert mission.phase is Phase.TUMBLING and kit.sequencer.safe_entries == 0
    assert again.driver.samples >= 4 and again.driver.calibrations >= 1
    again.close()
