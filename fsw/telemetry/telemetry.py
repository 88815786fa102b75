"""Telemetry out: the MAVLink messages the flight software sends, built from the dialect bindings.

Everything on the wire is defined once, in `debris.xml` (+ common.xml); this module only fills the
generated message classes. A failed write (serial port gone, network down) is counted, never raised
into the flight loop.

Rates and link budget (57,600 baud radio, 8N1 = 5,760 B/s): see docs/telemetry.md, "Link budget".
"""
from __future__ import annotations

import math

import struct

import numpy as np

from .dialect import mavlink
from .signing import SigningClock, setup_outgoing, sign_ready
from .store_forward import StoreForward

GAUSS_PER_TESLA = 1e4
#: counters since start go out modulo 2³² in their uint32 fields, as MAVLink's own do (a frame the encoder
#: refused would be lost for good): a loop at 1 kHz counts past 2³² ticks in 50 days
U32 = 0xFFFFFFFF

def usec(t_s: float) -> int:
    return int(round(t_s * 1e6))


class Telemetry:
    """Sends the flight software's messages on a pymavlink connection bound to the dialect.

    `store`: the store-and-forward buffer (`fsw.telemetry.store_forward`; None: what cannot be sent
    is lost). `key` + `clock`: sign every frame with the mission key (`fsw.telemetry.signing`).
    Call :meth:`service` once per loop tick: it sets the signing time, retries a link that is down
    and replays stored frames within the replay budget.

    `rates` (a `fsw.telemetry.services.MessageRates`, set by the services; None: every message at its
    own rate): what is sent on the box's own schedule goes out only when its interval allows (the
    ground's MAV_CMD_SET_MESSAGE_INTERVAL); answers (:meth:`send_now`) and what is sent through
    :meth:`ungated` (a requested message) always go. `latest`: the last instance of every message
    sent, by id (MAV_CMD_REQUEST_MESSAGE sends it again).
    """

    def __init__(self, conn, *, store: StoreForward | None = None, key: bytes | None = None,
                 clock: SigningClock | None = None, link_id: int = 0) -> None:
        self.conn = conn
        self.mav = conn.mav
        self.frames_sent = 0
        self.send_errors = 0
        self.encode_errors = 0
        self.last_error = ""
        self.store = store
        self.clock = clock if clock is not None else SigningClock()
        self.signed = key is not None
        if key is not None:
            setup_outgoing(self.mav, key, self.clock, link_id)
        self.rates = None
        self.latest: dict[int, object] = {}
        self._now_s = 0.0
        self._gated = True

    def service(self, now_s: float, max_replay_frames: int = 16) -> None:
        """Once per loop tick, before sending: signing time, link retry, replay of stored frames."""
        self._now_s = now_s
        if self.signed:
            sign_ready(self.mav, self.clock, now_s)
        sf = self.store
        if sf is None:
            return
        sf.poll(now_s)
        if not sf.link_up and sf.may_send() and getattr(self.conn, "portdead", False) \
                and hasattr(self.conn, "reset"):
            self.conn.reset()  # pymavlink serial: reopen the port
        for _ in range(max_replay_frames):
            msg = sf.next_replay()
            if msg is None:
                break
            n = self._write(msg)
            if n is None:
                sf.write_failed()
                break
            sf.replay_sent(n)

    def send(self, msg) -> None:
        """Send a message on the box's own schedule (its rate may be set by the ground; kept while the link
        is down)."""
        self._send(msg)

    def ungated(self, fn, *args) -> None:
        """Run `fn(*args)`, whose messages go out whatever their rate setting (a requested message)."""
        self._gated = False
        try:
            fn(*args)
        finally:
            self._gated = True

    def _send(self, msg) -> None:
        mid = msg.id
        self.latest[mid] = msg
        if self._gated and self.rates is not None and not self.rates.due(mid, self._now_s):
            return
        sf = self.store
        if sf is not None and not sf.may_send():
            sf.keep(msg)
            return
        n = self._write(msg)
        if sf is not None:
            if n is None:
                sf.write_failed()
                sf.keep(msg)
            else:
                sf.write_ok()

    def send_now(self, msg) -> bool:
        """Send a reply (COMMAND_ACK, PARAM_VALUE) now or never: it is not stored."""
        n = self._write(msg)
        if self.store is not None:
            self.store.write_failed() if n is None else self.store.write_ok()
        return n is not None

    def _write(self, msg) -> int | None:
        """Pack and write one frame: its length (0: could not be encoded, counted), or None when the
        link refused it (counted in send_errors). Never raises."""
        mav = self.mav
        try:
            buf = msg.pack(mav)
        except struct.error as e:  # a value out of its field's range: a bug, counted, never fatal
            self.encode_errors += 1
            self.last_error = repr(e)
            return 0
        try:
            result = self.conn.write(buf)
        except (OSError, ValueError) as e:  # link down, port closed: counted, the loop goes on
            self.send_errors += 1
            self.last_error = repr(e)
            return None
        if result == -1 or getattr(self.conn, "portdead", False):  # pymavlink serial: port dead
            self.send_errors += 1
            self.last_error = "port dead"
            return None
        mav.seq = (mav.seq + 1) % 256
        mav.total_packets_sent += 1
        mav.total_bytes_sent += len(buf)
        self.frames_sent += 1
        return len(buf)

    @property
    def bytes_sent(self) -> int:
        return self.mav.total_bytes_sent

    def heartbeat(self) -> None:
        """HEARTBEAT: a spacecraft (MAV_TYPE_SPACECRAFT_ORBITER) whose autopilot is the box
        (MAV_AUTOPILOT_GENERIC): ground stations (MAVProxy) take a heartbeat with MAV_AUTOPILOT_INVALID for
        a peripheral, never a vehicle, and never show it online."""
        self._send(mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_SPACECRAFT_ORBITER, mavlink.MAV_AUTOPILOT_GENERIC, 0, 0,
            mavlink.MAV_STATE_ACTIVE, 3))

    def sys_status(self, *, mag_healthy: bool, load_permille: int, errors_comm: int,
                   drop_rate_comm_centipercent: int = 0, errors_count=(0, 0, 0, 0)) -> None:
        """`errors_count`: SYS_STATUS errors_count1..4 (docs/link-and-security.md, "Faults survived")."""
        mag = mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG
        e1, e2, e3, e4 = (min(max(int(e), 0), 65535) for e in errors_count)
        self._send(mavlink.MAVLink_sys_status_message(
            mag, mag, mag if mag_healthy else 0, min(max(load_permille, 0), 1000),
            65535, -1, -1, min(drop_rate_comm_centipercent, 10000), min(errors_comm, 65535), e1, e2, e3, e4))

    def link_status(self, t_s: float, *, cmd_accepted: int, rejected_unsigned: int,
                    rejected_bad_signature: int, rejected_replay: int, rejected_invalid: int,
                    uplink_bytes: int = 0, uplink_bytes_dropped: int = 0, uplink_garbage_bytes: int = 0,
                    uplink_bad_crc: int = 0, uplink_foreign_datagrams: int = 0, uplink_os_dropped: int = 0) -> None:
        """DEBRIS_LINK_STATUS: uplink security and flood counters, this link's store-and-forward state."""
        sf = self.store
        u32 = 0xFFFFFFFF
        self._send(mavlink.MAVLink_debris_link_status_message(
            usec(t_s), *(min(int(x), u32) for x in (cmd_accepted, rejected_unsigned, rejected_bad_signature,
                                                    rejected_replay, rejected_invalid)),
            *(min(int(x), u32) for x in ((sf.buffered, sf.replayed, sf.dropped) if sf else (0, 0, 0))),
            1 if sf is None or sf.link_up else 0, (self.frames_sent + 1) & u32,
            *(int(x) & u32 for x in (uplink_bytes, uplink_bytes_dropped, uplink_garbage_bytes, uplink_bad_crc,
                                     uplink_foreign_datagrams, uplink_os_dropped))))

    def mag_sample(self, t_s: float, b_T: np.ndarray, seq: int, run_id: int, flags: int = 0,
                   kit_T: np.ndarray | None = None) -> None:
        """DEBRIS_MAG_SAMPLE: the numbered sample (field in gauss), live; `flags`: DEBRIS_SAMPLE_FLAGS;
        `kit_T`: the kit's field the box took out of it (the kit_mag extension; zero ones cost no bytes)."""
        g = b_T * GAUSS_PER_TESLA
        self._send(mavlink.MAVLink_debris_mag_sample_message(
            usec(t_s), seq & 0xFFFFFFFF, run_id, [float(g[0]), float(g[1]), float(g[2])], int(flags),
            _gauss3(kit_T)))

    def resend_sample(self, seq: int, run_id: int, t_us: int, b_T: np.ndarray, flags: int = 0,
                      kit_T: np.ndarray | None = None) -> int | None:
        """DEBRIS_MAG_SAMPLE flagged RESENT (with the flags and kit field it was stored with), from the
        sample store: the bytes written, or None while the link is down (nothing is stored for later:
        the ground asks again)."""
        sf = self.store
        if sf is not None and not sf.link_up:
            return None
        g = b_T * GAUSS_PER_TESLA
        n = self._write(mavlink.MAVLink_debris_mag_sample_message(
            t_us, seq & 0xFFFFFFFF, run_id, [float(g[0]), float(g[1]), float(g[2])],
            (int(flags) | mavlink.DEBRIS_SAMPLE_FLAGS_RESENT) & 0xFF, _gauss3(kit_T)))
        if sf is not None:
            sf.write_failed() if n is None else sf.write_ok()
        return n

    def sample_store_status(self, t_s: float, store, resender) -> None:
        """DEBRIS_SAMPLE_STORE (`fsw.telemetry.sample_store`)."""
        u32 = 0xFFFFFFFF
        self._send(mavlink.MAVLink_debris_sample_store_message(
            usec(t_s), store.run_id, store.run_first_seq & u32, store.first_seq & u32, store.next_seq & u32,
            min(resender.queued, u32), resender.resent & u32, resender.requests & u32, resender.refused & u32,
            1 if store.persistent else 0))

    def rate_estimate(self, t_s: float, omega_radps: np.ndarray, sigma_radps: np.ndarray,
                      method: int, flags: int) -> None:
        w, s = omega_radps, sigma_radps
        self._send(mavlink.MAVLink_debris_rate_estimate_message(
            usec(t_s), float(w[0]), float(w[1]), float(w[2]), float(s[0]), float(s[1]), float(s[2]),
            method, flags))

    def attitude(self, t_s: float, q, omega_radps, sigma_att_rad, sigma_radps, *, filter_id: int, flags: int,
                 handovers: int) -> None:
        """The flown filter's attitude: ATTITUDE_QUATERNION (q body → ECI, w first, and the body rates;
        only when the filter has an attitude, `q` not None) and DEBRIS_ATTITUDE_SIGMA (1-σ of the attitude
        about the body axes, NaN without one, and of the rate)."""
        if q is not None:
            w = omega_radps
            self._send(mavlink.MAVLink_attitude_quaternion_message(
                int(round(t_s * 1e3)) & 0xFFFFFFFF, *(float(x) for x in q), float(w[0]), float(w[1]), float(w[2]),
                [0.0, 0.0, 0.0, 0.0]))
        sa = [math.nan] * 3 if sigma_att_rad is None else [float(x) for x in sigma_att_rad]
        self._send(mavlink.MAVLink_debris_attitude_sigma_message(
            usec(t_s), sa, [float(x) for x in sigma_radps], int(filter_id), int(flags) & 0xFF,
            min(int(handovers), 0xFFFF)))

    def sim_state(self, t_s: float, omega_radps, q, b_T, moment_Nm) -> None:
        """SIMULATION ONLY truth (DEBRIS_SIM_STATE); sent by SITL, never on target."""
        g = b_T * GAUSS_PER_TESLA
        self._send(mavlink.MAVLink_debris_sim_state_message(
            usec(t_s), *(float(x) for x in omega_radps), [float(x) for x in q],
            *(float(x) for x in g), *(float(x) for x in moment_Nm)))

    def loop_status(self, t_s: float, *, ticks: int, overruns: int, task_overruns: int, period_s: float,
                    mean_us: float, p50_us: float, p99_us: float, max_us: float, sample_rate_hz: float = 0.0,
                    configured_sample_rate_hz: float = 0.0, sample_cost_us: float = 0.0, samples_taken: int = 0,
                    samples_dropped: int = 0, queue_depth: int = 0, queue_max_depth: int = 0) -> None:
        self._send(mavlink.MAVLink_debris_loop_status_message(
            usec(t_s), ticks & U32, overruns & U32, task_overruns & U32, period_s * 1e6, mean_us, p50_us, p99_us,
            max_us, sample_rate_hz, configured_sample_rate_hz, sample_cost_us, samples_taken & U32,
            samples_dropped & U32, min(queue_depth, 65535), min(queue_max_depth, 65535)))

    def mag_status(self, t_s: float, driver) -> None:
        o = driver.offset_T * GAUSS_PER_TESLA
        self._send(mavlink.MAVLink_debris_mag_status_message(
            usec(t_s), driver.samples & U32, driver.bus_errors & U32, driver.timeouts & U32, driver.bad_id & U32,
            min(driver.resets, 65535), int(driver.state), float(o[0]), float(o[1]), float(o[2]),
            driver.offset_jumps & U32, driver.offset_outliers & U32, driver.offset_disturbed & U32))

    def inertia_estimate(self, t_s: float, *, samples: int, inertia, ci95, ci99, state: int, flags: int) -> None:
        """DEBRIS_INERTIA_ESTIMATE: tensor (Ixx, Iyy, Izz, Ixy, Ixz, Iyz) kg·m² about the centre of mass in
        sensor axes, 95 %/99 % half-widths, experiment state, flags (`fsw.ident.IdentExperiment`)."""
        self._send(mavlink.MAVLink_debris_inertia_estimate_message(
            usec(t_s), int(samples), [float(x) for x in inertia], [float(x) for x in ci95],
            [float(x) for x in ci99], int(state), int(flags)))

    def deorbit_status(self, t_s: float, st) -> None:
        """DEBRIS_DEORBIT_STATUS from a `fsw.deorbit.kit.DeorbitStatus` (channel 0 = pitch, 1 = yaw)."""
        u16 = [min(int(x), 65535) for x in st.capsule_openings], [min(int(x), 65535) for x in st.magnet_turns]
        self._send(mavlink.MAVLink_debris_deorbit_status_message(
            usec(t_s), [int(x) for x in st.position_steps], [int(x) & 0xFFFFFFFF for x in st.steps_total],
            [float(x) for x in st.energy_J], u16[0], u16[1], min(int(st.interlock_violations), 65535),
            [int(x) for x in st.capsule_state], [int(x) for x in st.magnet_state], [int(x) for x in st.polarity],
            [int(x) for x in st.fault], int(st.controller_state)))

    def deorbit_attitude(self, t_s: float, a, held: int, truth_ypr=(math.nan, math.nan, math.nan)) -> None:
        """DEBRIS_DEORBIT_ATTITUDE from a `fsw.deorbit.onboard_attitude.AttitudeReport` (the controller's inputs);
        `truth_ypr`: SITL's true yaw, pitch, roll then (NaN on the target)."""
        self._send(mavlink.MAVLink_debris_deorbit_attitude_message(
            usec(t_s), float(a.yaw_rad), float(a.pitch_rad), float(a.roll_rad), [float(x) for x in a.rate_radps],
            [float(x) for x in a.pointing_sigma_rad], float(a.rate_sigma_radps), int(a.source),
            min(int(a.hypotheses), 255), min(int(held), 0xFFFFFFFF), [float(x) for x in truth_ypr]))

    def mission_status(self, t_s: float, phase: int, reason: int, time_in_phase_s: float, rate_radps: float,
                       rate_sigma_radps: float, ci95_pct: float, inertia_kgm2, energy_J) -> None:
        """DEBRIS_MISSION_STATUS (`fsw.deorbit.mission`): the phase, why, the tumble, the identification."""
        self._send(mavlink.MAVLink_debris_mission_status_message(
            usec(t_s), int(phase), int(reason), float(time_in_phase_s), float(rate_radps), float(rate_sigma_radps),
            float(ci95_pct), [float(x) for x in inertia_kgm2], [float(x) for x in energy_J]))

    def kit_field(self, t_s: float, channel: int, *, scale: float, scale_sigma: float, field_T, innovation_T: float,
                  fit_rms_T: float, steps: int, ill_conditioned: int, outliers: int, flagged: int,
                  moving: bool) -> None:
        """DEBRIS_KIT_FIELD: one channel of the on-board kit-field model (`fsw.deorbit.kit_field`)."""
        self._send(mavlink.MAVLink_debris_kit_field_message(
            usec(t_s), int(channel), int(bool(moving)), float(scale), float(scale_sigma),
            [float(x) * 1e6 for x in field_T], float(innovation_T) * 1e6, float(fit_rms_T) * 1e6,
            min(int(steps), 65535), min(int(ill_conditioned), 65535), min(int(outliers), 65535),
            min(int(flagged), 0xFFFFFFFF)))

    def system_time(self, t_s: float, utc_s: float) -> None:
        """SYSTEM_TIME: the onboard UTC estimate (0 when not set) and the loop time."""
        utc_us = int(round(utc_s * 1e6)) if utc_s == utc_s else 0
        self._send(mavlink.MAVLink_system_time_message(max(utc_us, 0), int(t_s * 1e3) & 0xFFFFFFFF))

    def time_orbit(self, t_s: float, **fields) -> None:
        """DEBRIS_TIME_ORBIT (`fsw.timeorbit.TimeOrbit.message_fields`)."""
        self._send(mavlink.MAVLink_debris_time_orbit_message(usec(t_s), **fields))

    def tle(self, line1: str, line2: str) -> None:
        """DEBRIS_TLE from the box: the TLE in force (target 0: to every ground station), so that a
        recording carries the orbit the box flies."""
        self._send(mavlink.MAVLink_debris_tle_message(0, 0, line1.encode("ascii"), line2.encode("ascii")))

    def statustext(self, text: str, severity: int = mavlink.MAV_SEVERITY_INFO) -> None:
        """STATUSTEXT (at most 50 characters, cut beyond): events such as the de-orbit kit's transitions."""
        self._send(mavlink.MAVLink_statustext_message(severity, text.encode("ascii", "replace")[:50]))

    def magcal(self, t_s: float, cal, *, state: int, samples: int, dropped: int, rejections: int,
               residual: float, rate_T_per_s=(0.0, 0.0, 0.0), drift_period_s: float | None = None,
               restored: int = 0) -> None:
        """DEBRIS_MAGCAL: the applied calibration (`fsw.estimation.magcal.Calibration`, b in µT, D's six
        terms), its 1-σ (NaN before any), state and counters; the hard iron's drift rate (µT/h) and the
        drift's period (0: a constant host); `restored`: 1 the calibration is one restored after a
        restart, 2 one was and the new samples dropped it."""
        sig = cal.sigma
        sig = np.where(np.isfinite(sig), sig, np.nan)
        D = cal.D
        terms = [D[0, 0], D[1, 1], D[2, 2], D[0, 1], D[0, 2], D[1, 2]]
        self._send(mavlink.MAVLink_debris_magcal_message(
            usec(t_s), min(int(samples), 0xFFFFFFFF), min(int(dropped), 0xFFFFFFFF), min(int(rejections), 65535),
            [float(x) * 1e6 for x in cal.b_T], [float(x) for x in terms], [float(x) * 1e6 for x in sig[:3]],
            [float(x) for x in sig[3:]], float(residual), int(state),
            [float(x) * 1e6 * 3600.0 for x in rate_T_per_s], float(drift_period_s or 0.0), int(restored)))


def _gauss3(b_T) -> list[float]:
    """A field in T as the three floats in gauss of a message (zeros for None)."""
    if b_T is None:
        return [0.0, 0.0, 0.0]
    return [float(b_T[0]) * GAUSS_PER_TESLA, float(b_T[1]) * GAUSS_PER_TESLA, float(b_T[2]) * GAUSS_PER_TESLA]
