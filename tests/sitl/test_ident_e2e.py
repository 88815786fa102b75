"""End to end in SITL: MAV_CMD_DEBRIS_IDENT_START → observe → the tug's torque in the simulator → observe →
the onboard fit → DEBRIS_INERTIA_ESTIMATE over UDP → decoded on the ground → refined on the ground from
the decoded recording; all against the simulator's truth."""
import dataclasses
import io
import threading
from types import SimpleNamespace

import numpy as np
import pytest

from hil import sitl
from fsw.ident import DONE
from fsw.telemetry import dialect
from fsw.telemetry.dialect import mavlink
from ground import inertia as ground_inertia
from ground.decode import Decoder
from support import free_udp_port
from support import flight_assumptions

pytestmark = pytest.mark.sitl
TRUTH = np.array([175.0, 200.0, 285.0, 0.0, 0.0, 0.0])
M = (0.2, 0.15, -0.1)


@pytest.fixture(scope="module")
def experiment():
    # Aist-2D with no torque of its own: the experiment's tug is the only one
    args = sitl.parse_args(["--scenario", "aist2d_ident", "--rate", "10", "--speed", "0", "--quiet"])
    # a calibrated magnetometer (the calibration on board takes an orbit, longer than this experiment)
    args = dataclasses.replace(args, scenario=flight_assumptions("aist2d_ident"))
    port = free_udp_port()
    rx = dialect.open_link(f"udpin:127.0.0.1:{port}", source_system=dialect.GCS_SYSID,
                           source_component=dialect.GCS_COMPID, input=True)
    tx = dialect.open_link(f"udpout:127.0.0.1:{port}", source_system=dialect.FSW_SYSID,
                           source_component=dialect.FSW_COMPID)
    decoder = Decoder()
    done = threading.Event()

    def receive():
        idle = 0
        while idle < 10:
            msg = rx.recv_match(blocking=True, timeout=0.1)
            if msg is None:
                idle = idle + 1 if done.is_set() else 0
                continue
            decoder.handle(msg, 0.0)

    box = sitl.build(args, link=tx, ident_options={"work_per_tick": 200000})
    scn, sim, fsw = box.scenario, box.sim, box.fsw
    ident = fsw.apps["ident"]
    th = threading.Thread(target=receive)
    th.start()
    start = SimpleNamespace(command=mavlink.MAV_CMD_DEBRIS_IDENT_START, confirmation=0, target_system=1,
                            target_component=1, param1=mavlink.DEBRIS_TORQUE_SOURCE_TUG, param2=60.0,
                            param3=120.0, param4=120.0, param5=M[0], param6=M[1], param7=M[2])
    results = []
    try:
        k = 0
        while ident.state != DONE and k < 20000:
            t = k / args.run.rate_hz
            sim.advance_to(t)
            if k == 5:   # a signed command verified by the uplink reaches the router as authenticated
                results.append(fsw.commands.handle(start, t, authenticated=True))
            fsw.tick(t)
            k += 1
    finally:
        done.set()
        th.join(timeout=30)
        rx.close()
        tx.close()
    return SimpleNamespace(fsw=fsw, ident=ident, sim=sim, scn=scn, decoder=decoder, results=results,
                           t_end=k / args.run.rate_hz)


def test_the_command_started_the_experiment_and_the_tug_acted(experiment):
    e = experiment
    assert e.results == [mavlink.MAV_RESULT_ACCEPTED]
    pulses = e.sim.scenario.torques
    assert len(pulses) == 1 and pulses[0].duration_s == pytest.approx(120.0)
    np.testing.assert_allclose(pulses[0].moment_Nm, M)
    assert pulses[0].start_s == pytest.approx(60.5, abs=0.11)
    assert e.ident.state == DONE and e.t_end < 400.0             # the final fit came within 100 s of the end
    # (loop overruns are wall-time measurements: reported, not asserted — see the benchmarks)


def test_onboard_estimate_against_truth(experiment):
    est = experiment.ident.result.estimate
    assert experiment.ident.result.final and est.samples_used == 300
    assert np.all(np.abs(est.p[:3] - TRUTH[:3]) / TRUTH[:3] < 0.02), est.p
    assert np.all(np.abs(est.p - TRUTH) <= 3 * est.ci95 + 1e-6)
    assert est.flags == 7
    assert len(experiment.ident.history) >= 2                     # running estimates before the final one


def test_decoded_on_the_ground(experiment):
    d = experiment.decoder
    msgs = d.inertia_estimates
    assert msgs and msgs[-1]["state_name"] == "done"
    assert {m["state_name"] for m in msgs} >= {"observe_free", "torque", "observe_after", "done"}
    last = msgs[-1]
    est = experiment.ident.result.estimate
    np.testing.assert_allclose(last["inertia_kgm2"], est.p, rtol=1e-6)   # float32 on the wire
    np.testing.assert_allclose(last["ci95_kgm2"], est.ci95, rtol=1e-6)
    np.testing.assert_allclose(last["ci99_kgm2"], est.ci99, rtol=1e-6)
    assert last["samples"] == 300 and last["flags"] == 7
    assert "I[done]" in d.status_line()


def test_ground_refines_from_the_decoded_recording(experiment, tmp_path):
    rec = experiment.decoder.recording()
    assert np.any(rec.m_Nm != 0)                                  # the tug's moment, from DEBRIS_SIM_STATE
    b_inertial, truth, _ = ground_inertia.field_model("aist2d_ident")
    np.testing.assert_allclose(truth, TRUTH)
    rep = ground_inertia.run(rec, b_inertial, sigma_b_T=1.5e-6, running_points=0)
    est = rep.estimate
    assert np.all(np.abs(est.p - TRUTH) <= 3 * est.ci95 + 1e-6), (est.p, est.ci95)
    # the same 300 samples as on board, refitted from their float32 copies: Izz's 95 % half-width is ~1.9 %
    assert np.all(np.abs(est.p[:3] - TRUTH[:3]) / TRUTH[:3] < 0.025)
    out = tmp_path / "inertia.json"
    ground_inertia.write_json(out, est)
    assert "I_kgm2" in out.read_text()


def test_sitl_main_wires_the_experiment():
    args = sitl.parse_args(["--scenario", "aist2d", "--duration", "1", "--speed", "0", "--quiet",
                                "--link", f"udpout:127.0.0.1:{free_udp_port()}"])
    run = sitl.run(args, out=io.StringIO())
    assert run.fsw.apps.get("ident") is not None
    assert {mavlink.MAV_CMD_DEBRIS_IDENT_START, mavlink.MAV_CMD_DEBRIS_IDENT_STOP} <= set(run.fsw.commands.registered())
    assert "ident" in [t.name for t in run.fsw.scheduler.tasks]
