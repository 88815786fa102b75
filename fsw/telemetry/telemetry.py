"""Telemetry out: the MAVLink messages the flight software sends, built from the dialect bindings.

Everything on the wire is defined once, in `debris.xml` (+ common.xml); this module only fills the
generated message classes. A failed write (serial port gone, network down) is counted, never raised
into the flight loop.

Rates and link budget (57,600 baud radio, 8N1 = 5,760 B/s): see README.md, "Link budget".
"""
from __future__ import annotations

import struct

import numpy as np

from .dialect import mavlink

GAUSS_PER_TESLA = 1e4

MAG_FIELDS_UPDATED = (mavlink.HIGHRES_IMU_UPDATED_XMAG | mavlink.HIGHRES_IMU_UPDATED_YMAG
                      | mavlink.HIGHRES_IMU_UPDATED_ZMAG)


def usec(t_s: float) -> int:
    return int(round(t_s * 1e6))


class Telemetry:
    """Sends the flight software's messages on a pymavlink connection bound to the dialect."""

    def __init__(self, conn) -> None:
        self.conn = conn
        self.mav = conn.mav
        self.frames_sent = 0
        self.send_errors = 0
        self.encode_errors = 0
        self.last_error = ""

    def _send(self, msg) -> None:
        try:
            self.mav.send(msg)
            self.frames_sent += 1
        except (OSError, ValueError) as e:  # link down, port closed: counted, the loop goes on
            self.send_errors += 1
            self.last_error = repr(e)
        except struct.error as e:  # a value out of its field's range: a bug, counted, never fatal
            self.encode_errors += 1
            self.last_error = repr(e)

    @property
    def bytes_sent(self) -> int:
        return self.mav.total_bytes_sent

    def heartbeat(self) -> None:
        self._send(mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0,
            mavlink.MAV_STATE_ACTIVE, 3))

    def sys_status(self, *, mag_healthy: bool, load_permille: int, errors_comm: int,
                   drop_rate_comm_centipercent: int = 0) -> None:
        mag = mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG
        self._send(mavlink.MAVLink_sys_status_message(
            mag, mag, mag if mag_healthy else 0, min(max(load_permille, 0), 1000),
            65535, -1, -1, min(drop_rate_comm_centipercent, 10000), min(errors_comm, 65535), 0, 0, 0, 0))

    def mag_sample(self, t_s: float, b_T: np.ndarray) -> None:
        """HIGHRES_IMU with the field in gauss; only the magnetometer bits set in fields_updated."""
        g = b_T * GAUSS_PER_TESLA
        self._send(mavlink.MAVLink_highres_imu_message(
            usec(t_s), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, float(g[0]), float(g[1]), float(g[2]),
            0.0, 0.0, 0.0, 0.0, MAG_FIELDS_UPDATED, 0))

    def rate_estimate(self, t_s: float, omega_radps: np.ndarray, sigma_radps: np.ndarray,
                      method: int, flags: int) -> None:
        w, s = omega_radps, sigma_radps
        self._send(mavlink.MAVLink_debris_rate_estimate_message(
            usec(t_s), float(w[0]), float(w[1]), float(w[2]), float(s[0]), float(s[1]), float(s[2]),
            method, flags))

    def sim_state(self, t_s: float, omega_radps, q, b_T, moment_Nm) -> None:
        """SIMULATION ONLY truth (DEBRIS_SIM_STATE); sent by SITL, never on target."""
        g = b_T * GAUSS_PER_TESLA
        self._send(mavlink.MAVLink_debris_sim_state_message(
            usec(t_s), *(float(x) for x in omega_radps), [float(x) for x in q],
            *(float(x) for x in g), *(float(x) for x in moment_Nm)))

    def loop_status(self, t_s: float, *, ticks: int, overruns: int, task_overruns: int, period_s: float,
                    mean_us: float, p50_us: float, p99_us: float, max_us: float) -> None:
        self._send(mavlink.MAVLink_debris_loop_status_message(
            usec(t_s), ticks, overruns, task_overruns, period_s * 1e6, mean_us, p50_us, p99_us, max_us))

    def mag_status(self, t_s: float, driver) -> None:
        o = driver.offset_T * GAUSS_PER_TESLA
        self._send(mavlink.MAVLink_debris_mag_status_message(
            usec(t_s), driver.samples, driver.bus_errors, driver.timeouts, driver.bad_id,
            min(driver.resets, 65535), int(driver.state), float(o[0]), float(o[1]), float(o[2])))
