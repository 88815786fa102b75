"""Soak run: the flight software in SITL for a long stretch of simulated time, under injected faults and
attacks, faster than real time; prints (and writes as JSON) what was injected and what survived.

    python -m bench.soak [--duration S] [--json FILE] [--seed N] [--scenario NAME]

In one process, in lockstep: the simulator and its register-level MMC5983MA, the flight software
(driver → sample gate → estimators → signed telemetry through the store-and-forward buffer; uplink with
signature checks and the command router), a radio link with faults (`hil.faults.FaultyLink`), and a
ground station: the decoder (`ground.decode.Decoder`, verifying signatures, over the byte-wise
`Deframer`), a tlog count, and a commander that sends genuine signed commands (retrying like the
MAVLink command protocol) and attacks:

- unsigned commands, commands signed with a wrong key,
- replays of a captured genuine command frame,
- the lock-out attack on pymavlink (a forged frame with the largest timestamp, then a genuine
  command that must still be obeyed);
- floods of the uplink at 1 MB/s in 5 s bursts (0xFE in 64 KB datagrams, 0xFD, random bytes), each
  with a genuine signed command in its middle that must be obeyed within 1 s, and bursts of datagrams
  from spoofed source addresses (`bench.link_attacks`): the uplink is modelled as datagrams with source
  addresses, like UDP (`hil.faults.FaultyDatagramLink`). The figures say the loop overruns during the
  floods (target 0), the probes' latency, and whether a stranger ever became the address the box
  answers.

Faults come from `hil.faults.make_schedule` (seeded): one at a time, every kind in turn. A fault is
*survived* when, within 10 s + half its duration after it ends, the flight software is back to
normal: for the magnetometer, the driver measures and the gate accepts a new sample; for the link,
the ground receives frames again and (after a disconnect) the store-and-forward buffer is empty. It is
*flagged* when the flight software (or, for link faults, the ground) counted it.

Samples lost end to end: magnetometer samples the flight software handed to telemetry that the
ground does not have at the end (the run ends with a quiet minute, so the buffer drains and the last
requests are answered). The box numbers and keeps its samples; the ground asks again for those that
did not arrive (`ground.gaps`), so the target is 0 whatever the link did.
"""
from __future__ import annotations

import functools
import json
import math
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bench.campaign import Run
from bench.campaign import options as campaign_options
from fsw.argtypes import ArgumentParser, check_paths_or_exit, finite_float, int_range
from fsw.files import write_atomic
from fsw.flight import FlightSoftware
from fsw.telemetry.dialect import FSW_COMPID, FSW_SYSID, mavlink
from fsw.telemetry.framing import Deframer
from fsw.telemetry.signing import TIMESTAMP_MAX, SigningClock, Verdict, sign_frame, unix_clock, unix_to_timestamp
from fsw.telemetry.telemetry import usec
from ground.command import GroundLink
from ground.decode import Decoder

from fsw.config import RunConfig
from hil import scenario as scenarios
from hil import sitl
from hil.faults import ALL_KINDS, LINK_KINDS, GROUND_ADDR, FaultInjector, FaultyDatagramLink, make_schedule
from .link_attacks import FLOOD_PROBE, Flooder, Spoofer

#: the simulated wall clock at the start (ground time stamps, signing clocks): 2025-06-15
UNIX0_S = 1_750_000_000.0
PROBE_COMMAND = mavlink.MAV_CMD_USER_1  # a no-op the soak registers: counts executions
COMMAND_EVERY_S = 15.0
ATTACK_EVERY_S = 40.0
ACK_TIMEOUT_S = 1.0
MAX_ATTEMPTS = 5
GROUND_EVERY_TICKS = 5
ATTACKS = ("unsigned", "bad_signature", "replay", "lockout")


@dataclass
class FaultRecord:
    kind: str
    start_s: float
    duration_s: float
    severity: float
    deadline_s: float
    marks: dict = field(default_factory=dict)
    flagged: bool = False
    survived: bool | None = None
    recovered_after_s: float | None = None

    def as_dict(self) -> dict:
        return {"kind": self.kind, "start_s": round(self.start_s, 3), "duration_s": round(self.duration_s, 3),
                "severity": self.severity, "flagged": self.flagged, "survived": bool(self.survived),
                "recovered_after_s": None if self.recovered_after_s is None else round(self.recovered_after_s, 3)}


class Commander:
    """The ground's command traffic: one genuine exchange every COMMAND_EVERY_S, an attack every
    ATTACK_EVERY_S."""

    def __init__(self, link: FaultyDatagramLink, key: bytes, clock: SigningClock, rng: np.random.Generator) -> None:
        self.link = link
        self.ground = GroundLink(link.ground_write, key, clock)
        self.unsigned = GroundLink(link.ground_write, None)
        self.stranger = GroundLink(link.ground_write, rng.bytes(32), SigningClock(epoch=clock.epoch))
        self.rng = rng
        self.nonce = 0
        self.pending: dict | None = None
        self.next_command_s = 5.0
        self.next_attack_s = 12.0
        self.attack_index = 0
        self.captured: bytes | None = None
        self.stats = Counter()
        self.attacks = Counter()
        self.genuine_nonces: set[int] = set()
        self.followup_due = False

    def tick(self, now_s: float) -> None:
        p = self.pending
        if p is not None and now_s - p["sent_s"] >= ACK_TIMEOUT_S:
            if p["attempts"] >= MAX_ATTEMPTS:
                self.stats["unanswered"] += 1
                self.pending = None
                # lost to the link's faults: another genuine command, until one is answered (a box locked
                # out by the forged timestamp would answer none)
                self.followup_due = self.followup_due or bool(p.get("after_lockout"))
            else:
                self._send(p, now_s)
        if self.pending is None and self.followup_due:  # the genuine command behind a lock-out attempt
            self.followup_due = False
            self.nonce += 1
            self.stats["started"] += 1
            self.pending = {"kind": "probe", "nonce": self.nonce, "attempts": 0, "sent_s": now_s,
                            "after_lockout": True}
            self._send(self.pending, now_s)
        if self.pending is None and now_s >= self.next_command_s:
            self.next_command_s = now_s + COMMAND_EVERY_S
            kind = ("probe", "param", "request")[self.stats["started"] % 3]
            self.stats["started"] += 1
            self.nonce += 1
            self.pending = {"kind": kind, "nonce": self.nonce, "attempts": 0, "sent_s": now_s}
            self._send(self.pending, now_s)
        if now_s >= self.next_attack_s:
            self.next_attack_s = now_s + ATTACK_EVERY_S
            self._attack(ATTACKS[self.attack_index % len(ATTACKS)], now_s)
            self.attack_index += 1

    def _send(self, p: dict, now_s: float) -> None:
        g = self.ground
        if p["kind"] == "probe":
            frame = g.command_long(PROBE_COMMAND, [0, 0, 0, 0, 0, 0, float(p["nonce"])], now_s,
                                   confirmation=p["attempts"])
            self.genuine_nonces.add(p["nonce"])
            self.captured = frame
        elif p["kind"] == "param":
            g.send(mavlink.MAVLink_param_set_message(FSW_SYSID, FSW_COMPID, b"SF_REPLAY_BPS", 2500.0,
                                                     mavlink.MAV_PARAM_TYPE_REAL32), now_s)
        else:
            g.command_long(mavlink.MAV_CMD_REQUEST_MESSAGE,
                           [mavlink.MAVLINK_MSG_ID_DEBRIS_LINK_STATUS, 0, 0, 0, 0, 0, 0], now_s,
                           confirmation=p["attempts"])
        p["attempts"] += 1
        p["sent_s"] = now_s
        self.stats["frames_sent"] += 1

    def _attack(self, kind: str, now_s: float) -> None:
        bad_nonce = -float(self.attack_index + 1)
        params = [0, 0, 0, 0, 0, 0, bad_nonce]
        if kind == "unsigned":
            self.unsigned.command_long(PROBE_COMMAND, params, now_s)
        elif kind == "bad_signature":
            self.stranger.command_long(PROBE_COMMAND, params, now_s)
        elif kind == "replay":
            if self.captured is None:
                return
            self.link.ground_write(self.captured)
        else:  # lock-out: a forged far-future timestamp on the ground's own stream, then a genuine command
            packer = mavlink.MAVLink(None, srcSystem=self.ground.sysid, srcComponent=self.ground.compid)
            raw = mavlink.MAVLink_command_long_message(FSW_SYSID, FSW_COMPID, PROBE_COMMAND, 0, *params).pack(packer)
            self.link.ground_write(sign_frame(self.rng.bytes(32), raw, self.ground.link_id, TIMESTAMP_MAX))
            self.stats["lockout_followups"] += 1
            # a genuine command right behind it (at the next tick, or once the one in flight is done) must be
            # obeyed
            self.followup_due = True
        self.attacks[kind] += 1

    def on_message(self, msg, verdict: Verdict | None) -> None:
        p = self.pending
        if p is None or verdict is not Verdict.OK:
            return
        kind = msg.get_type()
        done = False
        if kind == "COMMAND_ACK":
            want = PROBE_COMMAND if p["kind"] == "probe" else mavlink.MAV_CMD_REQUEST_MESSAGE
            done = p["kind"] != "param" and msg.command == want
        elif kind == "PARAM_VALUE":
            done = p["kind"] == "param" and msg.param_id == "SF_REPLAY_BPS"
        if done:
            self.stats["answered"] += 1
            if p.get("after_lockout"):
                self.stats["lockout_survived"] += 1
            self.pending = None


def _fault_marks(fsw: FlightSoftware, dec: Decoder) -> dict:
    src = fsw.source
    st = dec.stats.summary()
    tot = st["totals"]
    sf = fsw.tlm.store
    return {"timeouts": src.timeouts, "bus_errors": src.bus_errors, "bad_id": src.bad_id,
            "resets": src.resets, "chip_resets": src.chip_resets_detected,
            "refused": dict(fsw.gate.counts), "accepted": fsw.gate.accepted,
            "received": tot["received"], "lost": tot["lost"], "bad_crc": st["bad_crc"],
            "garbage": st["garbage_bytes"], "duplicates": tot["duplicates"], "late": tot["late"],
            "out_of_sequence": tot["out_of_sequence"], "outages": sf.outages}


def _flagged(kind: str, a: dict, b: dict) -> bool:
    """Whether the counters moved between the fault's start (a) and end (b)."""
    d = {k: (b[k] - a[k]) if not isinstance(a[k], dict) else {r: b[k][r] - a[k][r] for r in a[k]} for k in a}
    return {
        "no_data_ready": d["timeouts"] > 0,
        "bus_errors": d["bus_errors"] > 0,
        "stuck": d["refused"]["stuck"] > 0,
        "spike": sum(d["refused"].values()) > 0,
        "saturation": d["refused"]["saturated"] > 0,
        "chip_reset": d["chip_resets"] + d["timeouts"] + d["resets"] > 0,
        "wrong_id": d["bad_id"] > 0,
        "loss": d["lost"] > 0,
        "corruption": d["bad_crc"] + d["lost"] > 0,
        "garbage": d["garbage"] > 0,
        "duplicates": d["duplicates"] > 0,
        "reordering": d["late"] + d["out_of_sequence"] > 0,
        "disconnect": d["outages"] > 0,
    }[kind]


def run(duration_s: float = 3600.0, *, seed: int = 1, scenario: str = "isoi", rate_hz: float = 50.0,
        buffer_frames: int = 8192, kinds=ALL_KINDS, quiet_s: tuple[float, float] = (20.0, 60.0),
        progress=None) -> dict:
    """Run the soak; returns the figures (see the module docstring). `quiet_s`: spacing of the faults
    (shorter in the CI form, to fit every kind in a few simulated minutes)."""
    wall0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    rng_sched, rng_link, rng_fault, rng_cmd, rng_key = rng.spawn(5)
    key = rng_key.bytes(32)
    epoch = unix_to_timestamp(UNIX0_S)
    link = FaultyDatagramLink(rng_link, src_system=FSW_SYSID, src_component=FSW_COMPID)
    box = sitl.build(sitl.SitlConfig(RunConfig(rate_hz=rate_hz, buffer_frames=buffer_frames), scenario=scenario,
                                      seed=seed),
                     link=link, key=key, clock=SigningClock(epoch=epoch, clock_set=True), run_id=0, ident=False)
    scn, sim, fsw, tlm = box.scenario, box.sim, box.fsw, box.flight.tlm
    # the loop's work in this process's own CPU time: another process on the machine is not an overrun
    fsw.scheduler.work_timer = time.thread_time
    executions: list[float] = []
    fsw.commands.register(PROBE_COMMAND, lambda msg, now_s: executions.append(msg.param7))

    schedule = make_schedule(rng_sched, duration_s, kinds=kinds, quiet_s=quiet_s)
    injector = FaultInjector(schedule, sim.sensor, link, rng_fault, sample_period_s=1.0 / scn.sample_rate_hz)
    # the ground asks the box again for samples that did not arrive (signed, on a link id of its own)
    decoder = Decoder(key=key, requests=GroundLink(link.ground_write, key, unix_clock(), link_id=2))
    deframer = Deframer()
    commander = Commander(link, key, SigningClock(epoch=epoch, clock_set=True), rng_cmd)
    flooder, spoofer = _link_attackers(fsw, link, commander, key, epoch, executions, rng, duration_s)
    tlog_frames = 0
    samples_sent: list[int] = []
    outage_windows: list[tuple[float, float]] = []
    records: list[FaultRecord] = []
    open_records: dict[int, FaultRecord] = {}
    watching: list[FaultRecord] = []

    period = 1.0 / rate_hz
    n_ticks = int(round(duration_s * rate_hz))
    work = np.empty(n_ticks)
    next_progress = 600.0

    def ground(now_s: float) -> None:
        nonlocal tlog_frames
        data = link.ground_read()
        if not data:
            return
        unix = UNIX0_S + now_s
        for msg in deframer.feed(data):
            before = decoder.verifier.counts[Verdict.OK]
            decoder.handle(msg, unix)
            if msg.get_type() != "BAD_DATA":
                tlog_frames += 1
                ok = decoder.verifier.counts[Verdict.OK] > before
                commander.on_message(msg, Verdict.OK if ok else None)

    # everything on the box's clock (a scenario's [clock]: from hil.sitl's first reading, the schedule and
    # the ground's time stamps too), the simulator on the true time it means, as in SITL
    for k in range(n_ticks):
        t = box.t0_s + k * period
        for what, f in injector.update(t):
            if what == "start":
                rec = FaultRecord(f.kind, f.start_s, f.duration_s, f.severity, math.inf)
                rec.marks["start"] = _fault_marks(fsw, decoder)
                open_records[id(f)] = rec
                records.append(rec)
                if f.kind == "disconnect":
                    outage_windows.append((f.start_s, f.end_s))
            else:
                rec = open_records.pop(id(f))
                rec.marks["end"] = _fault_marks(fsw, decoder)
                rec.deadline_s = t + 10.0 + 0.5 * f.duration_s
                watching.append(rec)
        box.advance(t)
        flooder.tick(t, period, fsw.scheduler.stats.overruns)
        spoofer.tick(t, fsw.uplink)
        tlm_before = fsw.tlm_samples
        work[k] = fsw.tick(t)
        if fsw.tlm_samples > tlm_before:
            samples_sent.append(usec(fsw.sample_t_s))
        if k % GROUND_EVERY_TICKS == 0:
            ground(t)
            commander.tick(t)
        for rec in list(watching):
            if _recovered(rec, fsw, decoder):
                rec.survived, rec.recovered_after_s = True, t - (rec.start_s + rec.duration_s)
            elif t >= rec.deadline_s:
                rec.survived = False
            else:
                continue
            # flagged: the counters moved from the start of the fault to the recovery (or the deadline)
            rec.flagged = _flagged(rec.kind, rec.marks["start"], _fault_marks(fsw, decoder))
            watching.remove(rec)
        if progress is not None and t >= next_progress:
            next_progress += 600.0
            progress(f"t={t:7.0f} s  faults {len(records)}  frames {tlm.frames_sent}  "
                     f"buffered {tlm.store.buffered}")
    link.flush_held()
    ground(box.t0_s + duration_s)
    for msg in deframer.flush():
        decoder.handle(msg, UNIX0_S + box.t0_s + duration_s)
        if msg.get_type() != "BAD_DATA":
            tlog_frames += 1
    for rec in watching + list(open_records.values()):
        rec.survived = False
    flooder.finish(fsw.scheduler.stats.overruns)
    return _figures(locals())


def _link_attackers(fsw: FlightSoftware, link: FaultyDatagramLink, commander: Commander, key: bytes, epoch: int,
                    executions: list, rng: np.random.Generator, duration_s: float) -> tuple[Flooder, Spoofer]:
    """The floods and the spoofed sources (`bench.link_attacks`), with their own random streams."""
    rng_flood, rng_spoof = rng.spawn(2)
    flooder = Flooder(link, key, SigningClock(epoch=epoch, clock_set=True), rng_flood, duration_s=duration_s)
    fsw.commands.register(FLOOD_PROBE, lambda msg, now_s: flooder.executed(msg.param7, now_s))
    parser = Deframer()

    def replayable() -> bytes | None:  # the commander's last probe frame, once the box has obeyed it
        frame = commander.captured
        if frame is None:
            return None
        msg = parser.feed(frame)[0]
        return frame if msg.get_type() == "COMMAND_LONG" and msg.param7 in executions else None

    spoofer = Spoofer(link, rng_spoof, replayable, (commander.ground.sysid, commander.ground.compid),
                      PROBE_COMMAND, duration_s=duration_s, epoch=epoch)
    return flooder, spoofer


def _link_attack_figures(v: dict) -> dict:
    """The floods' and spoofed sources' figures."""
    fsw, link = v["fsw"], v["link"]
    u, peers, st = fsw.uplink.counters, fsw.uplink.peers, v["spoofer"].stats
    return {**v["flooder"].figures(),
            "uplink_bytes": u.bytes, "uplink_bytes_dropped": u.dropped_bytes,
            "uplink_garbage_bytes": u.garbage_bytes, "uplink_os_dropped": u.os_dropped,
            "uplink_foreign_datagrams": u.foreign_datagrams,
            "spoof_bursts": st.bursts, "spoofed_datagrams": st.datagrams, "spoofed_kinds": dict(st.kinds),
            "peer_table_capacity": peers.capacity, "peer_table_max": max(st.peer_table_max, len(peers)),
            "peer_table_evicted": peers.evicted,
            "answer_address_hijacked": st.answer_address_hijacked,
            "answer_address_is_ground": peers.answer_address == GROUND_ADDR,
            "uplink_datagrams_link_truth": link.truth["uplink_datagrams"]}


def _link_attack_report(fig: dict) -> list[str]:
    fl = fig["floods"]
    lat = fig["flood_probe_latency_max_s"]
    return [f"floods: {sum(fl.values())} bursts ({', '.join(f'{k} {n}' for k, n in fl.items())}), "
            f"{fig['flood_bytes'] / 1e6:.1f} MB at {fig['flood_rate_Bps'] / 1e6:g} MB/s"
            + (f" ({fig['flood_bytes_delivered'] / 1e6:.1f} MB reached the box, the rest met a link down)"
               if fig["flood_bytes_delivered"] < fig["flood_bytes"] else "") + "; loop overruns during "
            f"floods {fig['loop_overruns_during_floods']}; genuine command mid-flood obeyed within 1 s "
            f"{fig['flood_probes_obeyed_within_1s']} of {fig['flood_probes']}"
            + (f" (latency at most {lat:.2f} s)" if lat is not None else ""),
            f"uplink: {fig['uplink_bytes']} bytes in, {fig['uplink_bytes_dropped']} dropped over budget, "
            f"{fig['uplink_garbage_bytes']} garbage, {fig['uplink_os_dropped']} datagrams dropped by the "
            f"receive buffer, {fig['uplink_foreign_datagrams']} datagrams from unknown sources",
            f"spoofed sources: {fig['spoof_bursts']} bursts, {fig['spoofed_datagrams']} datagrams ("
            + ", ".join(f"{k} {n}" for k, n in sorted(fig["spoofed_kinds"].items()))
            + f"); source table at most {fig['peer_table_max']} of {fig['peer_table_capacity']}, "
              f"{fig['peer_table_evicted']} evicted; a stranger became the answer address "
              f"{fig['answer_address_hijacked']} times"]


def _recovered(rec: FaultRecord, fsw: FlightSoftware, dec: Decoder) -> bool:
    end = rec.marks["end"]
    if rec.kind in LINK_KINDS:
        ok = dec.stats.received() > end["received"]
        if rec.kind == "disconnect":
            ok = ok and fsw.tlm.store.buffered == 0 and fsw.tlm.store.link_up
        return ok
    return int(fsw.source.state) == mavlink.DEBRIS_MAG_STATE_MEASURE and fsw.gate.accepted > end["accepted"]


def _figures(v: dict) -> dict:
    fsw, tlm, decoder, link, commander = v["fsw"], v["tlm"], v["decoder"], v["link"], v["commander"]
    records = v["records"]
    seg = decoder._recorded()
    received = set(seg.mag_gauss)
    sent = v["samples_sent"]
    lost = [t for t in sent if t not in received]
    in_outage = [t for t in lost if any(a - 2.0 <= t * 1e-6 <= b + 2.0 for a, b in v["outage_windows"])]
    sf = tlm.store
    u = fsw.uplink.counters
    r = fsw.commands.counters
    stats = decoder.stats.summary()
    injected = Counter(rec.kind for rec in records)
    survived = Counter(rec.kind for rec in records if rec.survived)
    flagged = Counter(rec.kind for rec in records if rec.flagged)
    genuine = commander.genuine_nonces
    execs = Counter(v["executions"])
    obeyed = sum(n for nonce, n in execs.items() if nonce not in genuine) + sum(n - 1 for n in execs.values() if n > 1)
    st = fsw.scheduler.stats
    w_us = v["work"] * 1e6
    clock = v["sim"].clock
    return {
        "sim_seconds": v["duration_s"],
        "box_clock": {"offset_s": clock.offset_s, "drift_ppm": clock.drift_ppm, "box_end_s": v["t"],
                      "true_end_s": v["sim"].t_s},
        "wall_seconds": round(time.perf_counter() - v["wall0"], 2),
        "seed": v["seed"], "scenario": v["scenario"], "loop_rate_hz": v["rate_hz"],
        "faults_injected": dict(sorted(injected.items())),
        "faults_survived": dict(sorted(survived.items())),
        "faults_flagged": dict(sorted(flagged.items())),
        "faults": [rec.as_dict() for rec in records],
        "commands_sent": commander.stats["started"],
        "commands_answered": commander.stats["answered"],
        "commands_unanswered": commander.stats["unanswered"],
        "commands_executed": len(v["executions"]),
        "command_retries_answered_from_cache": r.retries,
        "attacks": dict(commander.attacks),
        "attacks_obeyed": obeyed,
        "lockout_attempts_survived": commander.stats["lockout_survived"],
        "commands_rejected": {"unsigned": u.unsigned + r.unauthenticated, "bad_signature": u.bad_signature,
                              "replay": u.replay, "future_timestamp": u.future,
                              "invalid": r.unsupported + r.denied + r.failed + u.params_refused},
        "frames_sent": tlm.frames_sent,
        "frames_received": stats["totals"]["received"],
        "frames_lost": stats["totals"]["lost"],
        "frames_lost_link_truth": link.truth["frames_lost"],
        "frames_corrupted_in_signature_link_truth": link.truth["frames_corrupted_in_signature"],
        "frames_duplicated": stats["totals"]["duplicates"],
        "frames_late": stats["totals"]["late"],
        "frames_recovered_by_replay": sf.replayed,
        "frames_dropped_buffer_full": sf.dropped,
        "frames_refused_signature": dict(decoder.unauthenticated),
        "tlog_frames": v["tlog_frames"],
        "frames_delivered_intact_link_truth": link.truth["frames_delivered_intact"],
        "link_outages": sf.outages,
        "samples_sent": len(sent),
        "samples_received": len(received),
        "samples_replayed": seg.late,
        "samples_lost": len(lost),
        "samples_lost_in_outages": len(in_outage),
        "sample_requests_sent": decoder.requests_sent,
        "samples_resent": fsw.resender.resent,
        "sample_requests_refused_on_board": fsw.resender.refused,
        "samples_refused_by_gate": dict(fsw.gate.counts),
        "loop_overruns": st.overruns,
        "task_overruns": st.task_overruns,
        "loop_work_p99_us": round(float(np.percentile(w_us, 99)), 1) if len(w_us) else 0.0,
        "loop_work_max_us": round(float(w_us.max()), 1) if len(w_us) else 0.0,
        "loop_period_us": round(1e6 / v["rate_hz"], 1),
        **_link_attack_figures(v),
    }


def report(fig: dict) -> str:
    """The figures as text."""
    lines = [f"soak: {fig['sim_seconds']:.0f} s simulated in {fig['wall_seconds']:.1f} s wall "
             f"({fig['sim_seconds'] / max(fig['wall_seconds'], 1e-9):.0f}x real time), scenario {fig['scenario']}, "
             f"seed {fig['seed']}, loop {fig['loop_rate_hz']:g} Hz",
             "faults              injected  flagged  survived"]
    for kind in ALL_KINDS:
        n = fig["faults_injected"].get(kind, 0)
        if n:
            lines.append(f"  {kind:<18s} {n:6d}  {fig['faults_flagged'].get(kind, 0):7d}  "
                         f"{fig['faults_survived'].get(kind, 0):8d}")
    tot = sum(fig["faults_injected"].values())
    lines.append(f"  {'total':<18s} {tot:6d}  {sum(fig['faults_flagged'].values()):7d}  "
                 f"{sum(fig['faults_survived'].values()):8d}")
    rej = fig["commands_rejected"]
    lines.append(f"commands: {fig['commands_sent']} genuine sent, {fig['commands_answered']} answered, "
                 f"{fig['commands_unanswered']} unanswered (link faults), {fig['commands_executed']} probe executions")
    lines.append("attacks: " + ", ".join(f"{k} {n}" for k, n in sorted(fig["attacks"].items()))
                 + f"; obeyed {fig['attacks_obeyed']}; genuine command right after a lock-out attempt obeyed "
                   f"{fig['lockout_attempts_survived']} times")
    lines.append("rejected on board: " + ", ".join(f"{k} {n}" for k, n in rej.items()))
    sig = fig["frames_refused_signature"].get("bad_signature", 0)
    lines.append(f"frames: sent {fig['frames_sent']}, received {fig['frames_received']}, lost {fig['frames_lost']} "
                 f"+ {sig} refused for a damaged signature (link truth {fig['frames_lost_link_truth']}, of which "
                 f"{fig['frames_corrupted_in_signature_link_truth']} in the signature), "
                 f"duplicates {fig['frames_duplicated']}, "
                 f"late {fig['frames_late']}, recovered by replay {fig['frames_recovered_by_replay']}, "
                 f"dropped (buffer full) {fig['frames_dropped_buffer_full']}; tlog {fig['tlog_frames']} "
                 f"(intact deliveries {fig['frames_delivered_intact_link_truth']})")
    lines.append(f"samples: sent {fig['samples_sent']}, received {fig['samples_received']} "
                 f"({fig['samples_replayed']} replayed after {fig['link_outages']} outages), "
                 f"lost {fig['samples_lost']} "
                 f"(in outages {fig['samples_lost_in_outages']}); asked again {fig['sample_requests_sent']} times, "
                 f"{fig['samples_resent']} sent again; refused by the gate: "
                 + ", ".join(f"{k} {n}" for k, n in fig["samples_refused_by_gate"].items()))
    lines.append(f"loop: overruns {fig['loop_overruns']}, task overruns {fig['task_overruns']}, work p99 "
                 f"{fig['loop_work_p99_us']:.0f} us, max {fig['loop_work_max_us']:.0f} us "
                 f"(period {fig['loop_period_us']:.0f} us)")
    lines += _link_attack_report(fig)
    return "\n".join(lines)


def soak_task(spec: Run, *, duration_s: float, scenario: str, rate_hz: float, progress=None) -> dict:
    """A campaign's task: the soak seeded by the run's seed."""
    return run(duration_s, seed=spec.seed[0], scenario=scenario, rate_hz=rate_hz, progress=progress)


def _progress(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = ArgumentParser(prog="python -m bench.soak", description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=finite_float(120), default=3600.0, metavar="S",
                    help="simulated seconds, >= 120: faults start at 30 s and the last minute is quiet "
                         "(default 3600; at least 300 for a meaningful schedule)")
    ap.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    ap.add_argument("--seed", type=int_range(0), default=1, help="seed of faults, link, simulator (default 1)")
    ap.add_argument("--scenario", default="isoi", help="SITL scenario (default isoi)")
    ap.add_argument("--rate", type=finite_float(0, 1000, min_exclusive=True), default=50.0, metavar="HZ",
                    help="loop rate (default 50)")
    ap.add_argument("--quiet", action="store_true", help="no progress lines")
    campaign_options.add_arguments(ap)
    args = ap.parse_args(argv)
    campaign_options.check(ap, args)
    scenario_file = args.scenario if Path(args.scenario).is_file() else None
    check_paths_or_exit(ap, inputs={"--scenario": scenario_file},
                        outputs={"--json": args.json, **campaign_options.outputs(args)})
    try:
        scenarios.load(args.scenario)
    except scenarios.ScenarioError as e:
        ap.error(f"--scenario: {e}")
    # one run, as a campaign (bench.campaign): here by default, on a cluster with --scheduler, kept with --results
    spec = Run(f"seed{args.seed}", (args.seed,), {})
    config = {"benchmark": "bench.soak", "duration_s": args.duration, "scenario": args.scenario, "rate_hz": args.rate}
    fn = functools.partial(soak_task, duration_s=args.duration, scenario=args.scenario, rate_hz=args.rate,
                           progress=None if args.quiet else _progress)
    got = campaign_options.execute(ap, args, fn, [spec], config, name="soak")
    if isinstance(got, int):  # --rerun, or the run failed
        return got
    fig = got[0]
    print(report(fig))
    if args.json:
        write_atomic(args.json, json.dumps(fig, indent=1))  # never a half-written file
        print(f"wrote {args.json}")
    ok = fig["attacks_obeyed"] == 0 and fig["samples_lost"] == 0 and \
        sum(fig["faults_survived"].values()) == sum(fig["faults_injected"].values()) and \
        fig["loop_overruns_during_floods"] == 0 and fig["answer_address_hijacked"] == 0 and \
        fig["flood_probes_obeyed_within_1s"] == fig["flood_probes"]
    return 0 if ok else 1


if __name__ == "__main__":
    from fsw.startup import exit_with

    exit_with(main)
