"""The mission's sequencer (`fsw.deorbit.mission`): every automatic transition on its criterion, the
commands, safe mode, the kit's magnets as the experiment's, telemetry decoded on the ground. The kit is
the flight software's on the emulator; the rate filter and the experiment's fit are stand-ins whose
numbers the tests set."""
import math
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np
import pytest

from fsw.commands import BadParam
from fsw.deorbit.detumble import DetumbleLaw, rotate_about
from fsw.deorbit.kit import DeorbitKit
from fsw.deorbit.mission import KitMagnets, Mission, MissionConfig, Phase, Reason, ci95_pct
from fsw.deorbit.onboard_attitude import EstimatedAttitude
from fsw.deorbit.sequencer import KitMode
from fsw.estimation.orbital_attitude import SpacecraftModel
from fsw.estimation.inertia import InertiaEstimate
from fsw.ident import ABORTED, DONE, IDLE, MAGNETS, OBSERVE_FREE
from fsw.telemetry.dialect import mavlink
from fsw.telemetry.telemetry import Telemetry
from ground.decode import Decoder
from hil.deorbit_kit import DeorbitKitEmulator
from support import Capture

pytestmark = pytest.mark.fsw

DT = 0.5
ACCEPTED, DENIED, FAILED = mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_DENIED, mavlink.MAV_RESULT_FAILED
TRUE_P = np.array([22.5, 24.9, 12.2, 0.35, -0.25, 0.3])
B0_T = np.array([20e-6, -10e-6, 30e-6])   # the samples: this field turning in the body with the set rate


class Rates:
    """The flown filter as the mission reads it."""

    NO_ESTIMATE = 4

    def __init__(self):
        self.omega_radps = np.radians([2.0, -2.5, 1.5])
        self.sigma_radps = np.full(3, math.radians(1.0))
        self.flags = 0


class Ident:
    """The experiment's commands and results; `finish(ci95)` ends it with that 95 % half-width."""

    def __init__(self):
        self.state, self.result, self.restored, self.started, self.stopped = IDLE, None, None, [], 0

    def cmd_start(self, msg, now_s):
        self.started.append((now_s, msg.param1, msg.param2, msg.param3, msg.param4))
        self.state = OBSERVE_FREE
        return mavlink.MAV_RESULT_ACCEPTED

    def cmd_stop(self, msg, now_s):
        self.stopped += 1
        self.state = ABORTED
        return mavlink.MAV_RESULT_ACCEPTED

    def adopt(self, estimate):
        self.result = SimpleNamespace(estimate=estimate, final=True)

    def finish(self, ci95_kgm2, shift_kgm2=0.0):
        est = InertiaEstimate(TRUE_P + shift_kgm2, np.diag(np.full(6, (ci95_kgm2 / 1.96) ** 2)), "test", 3000)
        self.result = SimpleNamespace(estimate=est, final=True)
        self.state = DONE


class Box:
    def __init__(self, config=None):
        self.emu = DeorbitKitEmulator()
        self.kit = DeorbitKit(self.emu, EstimatedAttitude(1.5e-6))
        self.ident, self.rates = Ident(), Rates()
        self.cap = Capture()
        self.tlm = Telemetry(self.cap)
        self.mission = Mission(self.kit, self.ident, rates=self.rates, config=config or MissionConfig())
        self.t = 0.0

    def run(self, seconds, sample=True):
        for _ in range(int(round(seconds / DT))):
            self.t = round(self.t + DT, 9)
            self.emu.advance_to(self.t)
            b = rotate_about(B0_T, -self.rates.omega_radps * self.t)
            s = SimpleNamespace(t_s=self.t, b_T=b) if sample else None
            self.kit.tick(self.t)
            self.mission.tick(self.t, s)
            self.mission.telemetry(self.t, self.tlm)

    def trusted_rates(self, sigma_dps=0.1):
        self.rates.sigma_radps = np.full(3, math.radians(sigma_dps))

    def command(self, command, *params):
        p = list(params) + [0.0] * (7 - len(params))
        msg = SimpleNamespace(command=command, **{f"param{i + 1}": float(v) for i, v in enumerate(p)})
        handler = {mavlink.MAV_CMD_DEBRIS_MISSION_PHASE: self.mission.cmd_phase,
                   mavlink.MAV_CMD_DEBRIS_MISSION_SAFE: self.mission.cmd_safe}[command]
        return handler(msg, self.t)

    def to_identifying(self):
        self.trusted_rates()
        self.run(121.0)
        assert self.mission.phase is Phase.RATES_KNOWN
        self.run(30.0)   # the magnets home
        assert self.mission.phase is Phase.IDENTIFYING

    def to_detumbling(self):
        self.to_identifying()
        self.ident.finish(0.1)
        self.run(1.0)
        assert self.mission.phase is Phase.DETUMBLING


@pytest.fixture
def box():
    b = Box()
    yield b
    assert b.emu.interlock_violations == 0 and b.kit.sequencer.interlock_violations == 0


def test_rates_known_only_once_the_sigma_has_held(box):
    box.run(200.0)
    assert box.mission.phase is Phase.TUMBLING          # σ 1 °/s: not trusted
    box.trusted_rates(0.1)
    box.run(100.0)
    assert box.mission.phase is Phase.TUMBLING          # held 100 s of the 120 s
    box.rates.sigma_radps = np.full(3, math.radians(1.0))
    box.run(1.0)
    box.trusted_rates(0.1)
    box.run(100.0)
    assert box.mission.phase is Phase.TUMBLING          # the hold started again
    box.run(25.0)
    assert box.mission.phase is Phase.RATES_KNOWN and box.mission.reason is Reason.AUTOMATIC


def test_the_magnets_are_homed_then_the_experiment_starts_with_them(box):
    box.to_identifying()
    assert all(ch.stepper.polarity == 1 for ch in box.kit.sequencer.channels)
    (t, source, free, torque, after), = box.ident.started
    assert source == MAGNETS and (free, torque, after) == (300.0, 1500.0, 300.0)


def test_kit_magnets_open_both_capsules_and_report_the_dipole(box):
    box.to_identifying()
    magnets = KitMagnets(box.kit)
    assert magnets.open(box.t)
    box.run(3.0)
    np.testing.assert_allclose(magnets.dipole_body_Am2(), [0.0, 15.0, 15.0])
    np.testing.assert_allclose(box.emu.dipole_body_Am2(), [0.0, 15.0, 15.0], atol=1e-9)  # the truth agrees
    magnets.close(box.t)
    box.run(2.0)
    np.testing.assert_allclose(magnets.dipole_body_Am2(), 0.0)
    np.testing.assert_allclose(box.emu.dipole_body_Am2(), 0.0, atol=1e-9)


def test_an_accurate_tensor_starts_the_detumbling(box):
    box.to_detumbling()
    assert box.mission.ci95_pct == pytest.approx(100 * 0.1 / 24.9, rel=1e-3)
    np.testing.assert_allclose(np.diag(box.mission.J_kgm2), TRUE_P[:3])
    assert isinstance(box.kit.law, DetumbleLaw) and box.kit.mode is KitMode.RUNNING
    np.testing.assert_allclose(box.kit.law.J_kgm2, box.mission.J_kgm2)
    box.run(30.0)
    assert box.mission.law.decisions >= 4
    assert any(ch.capsule.openings for ch in box.kit.sequencer.channels)  # the law pulses the kit


def test_an_inaccurate_tensor_is_tried_again_then_safe(box):
    box.to_identifying()
    box.ident.finish(2.0)                 # 8 % of the largest moment
    box.run(1.0)   # the magnets are homed already: the second attempt starts at once
    (_, a, b, _), (_, c, d, _) = box.mission.transitions[-2:]
    assert (a, b, c, d) == (Phase.IDENTIFYING, Phase.RATES_KNOWN, Phase.RATES_KNOWN, Phase.IDENTIFYING)
    assert box.mission.phase is Phase.IDENTIFYING and len(box.ident.started) == 2
    box.ident.finish(2.0)
    box.run(1.0)
    assert box.mission.phase is Phase.SAFE and box.mission.reason is Reason.IDENT_FAILED
    assert box.kit.mode is KitMode.SAFE and box.mission.J_kgm2 is None


def test_two_attempts_that_agree_are_combined_and_judged_together(box):
    """Each attempt alone at 6.0 % (95 %) of the largest moment, their tensors 1 σ apart: combined, their
    information adds (half-widths / √2: 4.3 %) and the mission detumbles with the mean."""
    box.to_identifying()
    box.ident.finish(1.5, shift_kgm2=+0.39)
    box.run(1.0)
    assert box.mission.phase is Phase.IDENTIFYING and len(box.ident.started) == 2
    box.ident.finish(1.5, shift_kgm2=-0.39)
    box.run(1.0)
    assert box.mission.phase is Phase.DETUMBLING
    assert box.mission.transitions[-1][3] == "tensor of 2 attempts ci95 4.3 %"
    np.testing.assert_allclose(np.diag(box.mission.J_kgm2), TRUE_P[:3], atol=1e-9)
    est = box.ident.result.estimate        # the experiment's result is the combined one: sent and kept
    np.testing.assert_allclose(est.p, TRUE_P, atol=1e-9)
    np.testing.assert_allclose(est.ci95, 1.5 / math.sqrt(2), rtol=1e-4)  # z = 1.95996 vs 1.96
    assert "2 attempts combined" in est.method


def test_two_attempts_that_disagree_are_not_combined(box):
    """The second tensor 5 kg·m² below the first (more than 4 σ of their difference on every component):
    something changed between them; judged alone, the second fails and the mission goes to SAFE."""
    box.to_identifying()
    box.ident.finish(1.5)
    box.run(1.0)
    box.ident.finish(1.5, shift_kgm2=-5.0)
    box.run(1.0)
    assert box.mission.phase is Phase.SAFE and box.mission.J_kgm2 is None
    assert box.mission.transitions[-1][3] == "identification ci95 7.5 %"  # of its own largest moment, 19.9


def test_detumbled_hands_over_to_the_controller_with_the_identified_tensor(box):
    box.to_detumbling()
    box.rates.omega_radps = np.radians([0.05, 0.05, -0.05])
    box.run(290.0)
    assert box.mission.phase is Phase.DETUMBLING
    box.run(20.0)
    assert box.mission.phase is Phase.STABILISING
    assert box.kit.law is None and box.kit.mode is KitMode.RUNNING
    assert box.kit.controller.config.inertia_kgm2 == pytest.approx(tuple(TRUE_P[:3]))
    assert isinstance(box.kit.attitude, EstimatedAttitude)
    np.testing.assert_allclose(box.kit.attitude.model.J(), box.mission.J_kgm2)


@dataclass
class StubEstimate:
    """The controller's attitude source as the mission sees it: built like EstimatedAttitude, trusted when
    the test says so."""

    sigma_b_T: float
    model: SpacecraftModel = field(default_factory=SpacecraftModel)
    tuning: object = None
    gate: object = None
    provider: object = None
    trusted: bool = False
    reason: str = "stand-in"
    trust = False      # what every instance's `attitude` finds (set by the test)

    def observe(self, t_s, b_T, dipole_body_Am2):
        pass

    def attitude(self, now_s):
        self.trusted = StubEstimate.trust
        return None


def test_while_detumbling_the_attitude_estimate_starts_and_hands_over_once_trusted():
    """A slow tumble the rate filter cannot call detumbled (0.35 °/s, above 0.15): the controller's estimate
    (the identified tensor) starts once the smoothed rate is below 0.5 °/s, the kit's pulses held meanwhile;
    still untrusted after `estimate_retry_s` it is dropped and the pulses resume for as long; started again,
    and trusted for 300 s, it hands over to STABILISING and runs on."""
    StubEstimate.trust = False
    box = Box(MissionConfig(estimate_retry_s=1200.0))
    box.kit.attitude = StubEstimate(1.5e-6)
    box.to_detumbling()
    box.rates.omega_radps = np.radians([0.2, 0.2, -0.2])
    box.run(600.0)
    assert box.kit.attitude is None                      # smoothed from 3.5 °/s: not yet below 0.5

    def openings():
        return sum(ch.capsule.openings for ch in box.kit.sequencer.channels)
    box.run(600.0)
    first = box.kit.attitude
    assert isinstance(first, StubEstimate) and first.model.J() == pytest.approx(box.mission.J_kgm2)
    started = box.mission._estimate_t_s
    box.run(10.0)
    held = openings()
    box.run(started + 1150.0 - box.t)
    assert box.kit.attitude is first and openings() == held and box.mission.law.reason   # pulses held
    box.run(100.0)
    assert box.kit.attitude is None and box.mission.phase is Phase.DETUMBLING            # dropped
    box.run(1100.0)
    assert box.kit.attitude is None and openings() > held                                # pulses resumed
    box.run(150.0)
    kept = box.kit.attitude
    assert isinstance(kept, StubEstimate) and kept is not first                          # started again
    StubEstimate.trust = True
    box.run(290.0)
    assert box.mission.phase is Phase.DETUMBLING
    box.run(20.0)
    assert box.mission.phase is Phase.STABILISING and "attitude estimate trusted" in box.mission.reason_text
    assert box.kit.attitude is kept and box.kit.law is None
    assert box.emu.interlock_violations == 0


def test_an_estimate_settling_by_its_own_error_is_no_spin_up(box):
    # after a restart the flown filter may lock on ~1 °/s low with a σ of 0.2-0.3 °/s and then settle on
    # the truth: a rise of 0.6 °/s is within 0.5 °/s + 3 σ; a real spin-up still goes beyond it
    box.to_detumbling()
    box.trusted_rates(0.25)
    axis = np.ones(3) / math.sqrt(3.0)
    box.rates.omega_radps = np.radians(2.0 * axis)
    box.run(400.0)
    box.trusted_rates(0.2)
    box.rates.omega_radps = np.radians(2.63 * axis)
    box.run(600.0)
    assert box.mission.phase is Phase.DETUMBLING
    box.rates.omega_radps = np.radians(4.0 * axis)
    box.run(600.0)
    assert box.mission.phase is Phase.SAFE and box.mission.reason is Reason.SPIN_UP


def test_a_growing_tumble_sends_the_mission_to_safe(box):
    box.to_detumbling()
    box.rates.omega_radps = np.radians([1.0, 1.0, 1.0])
    box.run(1000.0)
    box.rates.omega_radps = np.radians([1.4, -1.6, 1.4])   # |ω| 1.73 → 2.54 °/s for a moment: noise
    box.run(20.0)
    box.rates.omega_radps = np.radians([1.0, 1.0, 1.0])
    box.run(60.0)
    assert box.mission.phase is Phase.DETUMBLING
    box.rates.omega_radps = np.radians([1.6, 1.6, 1.6])   # |ω| 1.73 → 2.77 °/s for good
    box.run(600.0)
    assert box.mission.phase is Phase.SAFE and box.mission.reason is Reason.SPIN_UP
    assert box.kit.mode is KitMode.SAFE and box.kit.law is None
    box.run(5.0)
    assert all(ch.capsule.closed for ch in box.kit.sequencer.channels)
    assert np.allclose(box.emu.dipole_body_Am2(), 0.0, atol=1e-9)


def test_the_kit_in_safe_mode_takes_the_mission_to_safe_with_its_reason(box):
    box.to_detumbling()
    box.kit.sequencer.enter_safe(box.t, "stall on pitch")
    box.run(1.0)
    assert box.mission.phase is Phase.SAFE and box.mission.reason is Reason.KIT_SAFE
    assert "stall on pitch" in box.mission.reason_text


def test_commands(box):
    assert box.command(mavlink.MAV_CMD_DEBRIS_MISSION_PHASE, 7) == DENIED
    assert box.command(mavlink.MAV_CMD_DEBRIS_MISSION_PHASE, math.nan) == DENIED
    assert box.command(mavlink.MAV_CMD_DEBRIS_MISSION_PHASE, 1.5) == DENIED
    assert box.command(mavlink.MAV_CMD_DEBRIS_MISSION_PHASE, int(Phase.STABILISING)) == FAILED  # no tensor
    assert box.mission.phase is Phase.TUMBLING
    box.run(1.0)
    assert box.command(mavlink.MAV_CMD_DEBRIS_MISSION_SAFE) == ACCEPTED
    assert box.mission.phase is Phase.SAFE and box.mission.reason is Reason.COMMANDED
    assert box.kit.mode is KitMode.SAFE
    box.run(3.0)
    assert box.command(mavlink.MAV_CMD_DEBRIS_MISSION_PHASE, int(Phase.DETUMBLING)) == ACCEPTED
    assert box.mission.phase is Phase.DETUMBLING and box.kit.mode is KitMode.RUNNING


def test_a_restored_tensor_skips_the_experiment(box):
    box.ident.restored = {"inertia": list(TRUE_P), "ci95": [0.2] * 6, "ci99": [0.3] * 6, "samples": 3000,
                          "flags": 0, "state": DONE}
    box.trusted_rates()
    box.run(125.0)
    assert box.mission.phase is Phase.DETUMBLING and not box.ident.started
    assert ci95_pct(box.ident.restored) == pytest.approx(100 * 0.2 / 24.9)


def test_status_and_phase_changes_are_decoded_on_the_ground(box):
    box.to_detumbling()
    box.run(5.0)
    dec = Decoder()
    for i, msg in enumerate(box.cap.messages()):
        dec.handle(msg, 1000.0 + i * 1e-3)
    m = dec.mission
    assert m["phase"] == "DETUMBLING" and m["reason"] == "automatic"
    assert m["inertia_kgm2"] == pytest.approx(tuple(TRUE_P[:3]), rel=1e-6)
    assert [p for _, p, _ in dec.mission_phases] == ["TUMBLING", "RATES_KNOWN", "IDENTIFYING", "DETUMBLING"]
    assert dec.mission_phases[-1][0] == pytest.approx(box.mission.t_phase_s, abs=1e-3)
    texts = [msg.text for msg in box.cap.messages() if msg.get_type() == "STATUSTEXT"]
    assert any(t.startswith("mission DETUMBLING") for t in texts)
    assert "mission: DETUMBLING" in dec.summary_text()


def test_energy_is_booked_to_the_phase_it_was_spent_in(box):
    box.to_detumbling()
    box.run(60.0)
    e = box.mission.energy_by_phase()
    total = box.kit.energy().total_J
    assert sum(e.values()) == pytest.approx(total, abs=0.2)
    assert e["RATES_KNOWN"] > 0 and e["DETUMBLING"] > 0 and e["TUMBLING"] == 0.0


@pytest.mark.parametrize("kind, value", [("stall", 1.0), ("stuck", 0.5)])
def test_a_kit_fault_while_detumbling_ends_in_safe_with_the_reason_and_the_magnets_screened(box, kind, value):
    """A stalled stepper (every pulse lost) or a capsule stuck half open: the sequencer's recovery fails,
    the kit latches the fault and goes SAFE, the mission follows with the kit's reason; the magnets are
    screened at the end (the truth: no dipole acting beyond what a stuck shutter leaves)."""
    box.to_detumbling()
    box.rates.omega_radps = np.radians([2.0, -2.5, 1.5])
    box.emu.inject(0, kind, value)
    box.run(600.0)
    assert box.mission.phase is Phase.SAFE and box.mission.reason is Reason.KIT_SAFE
    assert "pitch" in box.mission.reason_text or "fault" in box.mission.reason_text
    assert box.kit.mode is KitMode.SAFE and box.kit.law is None
    stuck = value if kind == "stuck" else 0.0
    assert np.linalg.norm(box.emu.dipole_body_Am2()) <= 15.0 * stuck + 1e-9
    assert box.kit.sequencer.channels[1].capsule.closed   # the healthy channel screened too


def test_a_refused_identification_is_said_once_and_tried_again_every_ten_seconds(box):
    """The experiment refuses to start (no field along the orbit on board: a stale TLE): the mission says
    so once, not at every tick (a STATUSTEXT a tick would take half the radio at 50 Hz), tries again every
    `ident_retry_s`, and starts as soon as it may."""
    refusals = []

    def refuse(msg, now_s):
        refusals.append(now_s)
        raise BadParam("no orbit/field model on board: TLE stale")
    accept, box.ident.cmd_start = box.ident.cmd_start, refuse
    box.trusted_rates()
    box.run(121.0)
    assert box.mission.phase is Phase.RATES_KNOWN
    box.run(120.0)
    texts = [m.text for m in box.cap.messages() if m.get_type() == "STATUSTEXT" and "refused" in m.text]
    assert len(texts) == 1 and texts[0].startswith("mission: identification refused: no orbit")  # 50 chars
    assert 8 <= len(refusals) <= 12 and np.all(np.diff(refusals) >= 10.0 - 1e-9)   # after the magnets home
    box.ident.cmd_start = accept
    box.run(10.5)
    assert box.mission.phase is Phase.IDENTIFYING
