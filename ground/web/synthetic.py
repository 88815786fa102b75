"""Synthetic telemetry of a box, signed with its key: the frames a station's load test and its tests send.

`SyntheticBox(sysid, key).frames(t_s)` packs what a box sends at one sample: DEBRIS_MAG_SAMPLE,
DEBRIS_RATE_ESTIMATE (Kalman, with σ), DEBRIS_SIM_STATE (truth), and about once a second HEARTBEAT,
ATTITUDE_QUATERNION, DEBRIS_ATTITUDE_SIGMA and DEBRIS_LINK_STATUS. The values are a body spinning at a
constant rate in a fixed field (`field_uT`, `rate_dps`), so that what is plotted can be checked. The box's
time is `t_s`; a load test passes the Unix time, which gives the latency of every plotted row directly.
"""
from __future__ import annotations

import math

from fsw.telemetry.dialect import FSW_COMPID, mavlink
from fsw.telemetry.signing import setup_outgoing, sign_ready, unix_clock


class _Sink:
    def write(self, b) -> None:
        pass


class SyntheticBox:
    """A box's telemetry, signed with `key` (None: unsigned)."""

    def __init__(self, sysid: int, key: bytes | None, *, rate_dps: tuple = (6.0, -5.0, 6.5),
                 field_uT: float = 40.0, run_id: int = 0x1234) -> None:
        self.sysid = sysid
        self.mav = mavlink.MAVLink(_Sink(), srcSystem=sysid, srcComponent=FSW_COMPID)
        self.clock = unix_clock()
        self.signed = key is not None
        if key is not None:
            setup_outgoing(self.mav, key, self.clock)
        self.rate_radps = tuple(math.radians(w) for w in rate_dps)
        self.field_uT = field_uT
        self.run_id = run_id
        self.seq = 0
        self._next_slow_s = -math.inf

    def field_at(self, t_s: float) -> tuple[float, float, float]:
        """The field (µT) at box time `t_s`: turning about z at ω_z."""
        a = self.rate_radps[2] * t_s
        return (self.field_uT * math.cos(a), -self.field_uT * math.sin(a), 0.5 * self.field_uT)

    def _pack(self, msg, now_s: float) -> bytes:
        if self.signed:
            sign_ready(self.mav, self.clock, now_s)
        frame = bytes(msg.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) % 256  # as MAVLink.send does: every frame its sequence number
        return frame

    def frames(self, t_s: float, now_s: float | None = None) -> list[bytes]:
        """The frames of one sample at box time `t_s` (s), signed at Unix time `now_s` (default `t_s`)."""
        now_s = t_s if now_s is None else now_s
        t_us = round(t_s * 1e6)
        b_gauss = [x / 100.0 for x in self.field_at(t_s)]
        w, sigma = self.rate_radps, (0.01, 0.02, 0.03)
        out = [
            mavlink.MAVLink_debris_mag_sample_message(t_us, self.seq, self.run_id, b_gauss, 0, [0.0, 0.0, 0.0]),
            mavlink.MAVLink_debris_rate_estimate_message(t_us, *w, *sigma, mavlink.DEBRIS_RATE_METHOD_KALMAN, 0),
            mavlink.MAVLink_debris_sim_state_message(t_us, *w, [1.0, 0.0, 0.0, 0.0], *b_gauss, 0.0, 0.0, 0.0),
        ]
        self.seq += 1
        if t_s >= self._next_slow_s:
            self._next_slow_s = t_s + 1.0
            half = 0.5 * self.rate_radps[2] * t_s
            out += [
                mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GENERIC, mavlink.MAV_AUTOPILOT_INVALID, 0, 0,
                                                  mavlink.MAV_STATE_ACTIVE, 3),
                mavlink.MAVLink_attitude_quaternion_message(round(t_s * 1e3) & 0xFFFFFFFF, math.cos(half), 0.0,
                                                            0.0, math.sin(half), *w, [0.0] * 4),
                mavlink.MAVLink_debris_attitude_sigma_message(t_us, [0.01, 0.01, 0.02], list(sigma),
                                                              mavlink.DEBRIS_RATE_FILTER_EULER, 0, 0),
                mavlink.MAVLink_debris_link_status_message(t_us, 0, 0, 0, 0, 0, 0, 0, 0, 1),
            ]
        return [self._pack(m, now_s) for m in out]
