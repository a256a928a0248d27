"""Build tlogs in tests from real pymavlink-encoded frames (MAVLink 1 or 2, any system/component)."""

from __future__ import annotations

import math

import numpy as np

from telemetry.frames import euler_zyx_to_matrix
from telemetry.geodesy import enu_to_geodetic
from telemetry.mavlink import dialect, new_parser, parse_tlog_bytes, tlog_record

m = dialect()
T0 = 1_750_000_000_000_000  # unix µs
ORIGIN = (47.0, 8.0, 500.0)


class TlogBuilder:
    def __init__(self) -> None:
        self._mavs: dict[tuple[int, int], object] = {}
        self.items: list[tuple[int, bytes]] = []

    def add(self, t_recv_us: int, msg, sysid: int = 1, compid: int = 1, v1: bool = False) -> bytes:
        key = (sysid, compid)
        if key not in self._mavs:
            self._mavs[key] = new_parser(sysid, compid)
        mav = self._mavs[key]
        raw = bytes(msg.pack(mav, force_mavlink1=v1))
        mav.seq = (mav.seq + 1) % 256  # pack() does not advance the sequence number; send() would
        self.items.append((int(t_recv_us), raw))
        return raw

    def data(self) -> bytes:
        return b"".join(tlog_record(t, raw) for t, raw in self.items)

    def records(self):
        return parse_tlog_bytes(self.data()).records


def heartbeat_autopilot():
    return m.MAVLink_heartbeat_message(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4, 3)


def heartbeat_gcs():
    return m.MAVLink_heartbeat_message(m.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0, 4, 3)


def line_position(t_s: float) -> np.ndarray:
    """Truth used by the factory flights: 5 m/s east, 2 m/s north, climbing 0.5 m/s from 30 m."""
    return np.array([5.0 * t_s, 2.0 * t_s, 30.0 + 0.5 * t_s])


def spinning_yaw(t_s: float) -> float:
    """Yaw (NED, rad) turning at 1 rad/s starting near +pi: wraps through ±pi early on."""
    return math.remainder(math.pi - 0.3 + 1.0 * t_s, 2 * math.pi)


def factory_flight(b: TlogBuilder, duration_s: float = 10.0, boot_unix_us: int = T0 - 100_000_000,
                   latency_us: int = 20_000, timesync: bool = True, system_time: bool = True,
                   quaternion: bool = False, v1: bool = False, start_us: int = T0, sysid: int = 1,
                   pos_fn=line_position, yaw_fn=spinning_yaw, pitch: float = 0.05, roll: float = -0.04,
                   gpi_hz: float = 10.0, skip=None):
    """Emit an autopilot's telemetry (true state at send time t, received at t + latency) into ``b``.

    ``skip(t_s)`` → True drops the position/attitude messages at that time (a telemetry gap).
    """
    n_att = int(duration_s * 20)
    b.add(start_us, heartbeat_autopilot(), sysid, 1, v1)
    for k in range(n_att + 1):
        t_s = k / 20.0
        t = start_us + int(t_s * 1e6)
        boot_ms = (t - boot_unix_us) // 1000
        # the state at t, stamped with the truncated boot ms (as autopilots do)
        t_true_s = t_s
        if skip is not None and skip(t_s):
            continue
        R = euler_zyx_to_matrix(yaw_fn(t_true_s), pitch, roll)
        if quaternion:
            from telemetry.quat import matrix_to_quat

            q = matrix_to_quat(R)
            if k % 2:
                q = -q  # the same attitude, opposite sign: slerp must not take the long way
            b.add(t + latency_us, m.MAVLink_attitude_quaternion_message(boot_ms, *q, 0, 0, 0, [0, 0, 0, 0]),
                  sysid, 1, v1)
        else:
            b.add(t + latency_us, m.MAVLink_attitude_message(boot_ms, roll, pitch, yaw_fn(t_true_s), 0, 0, 0),
                  sysid, 1, v1)
        if k % int(round(20 / gpi_hz)) == 0:
            lat, lon, alt = enu_to_geodetic(pos_fn(t_true_s), ORIGIN)
            b.add(t + latency_us, m.MAVLink_global_position_int_message(
                boot_ms, int(round(float(lat) * 1e7)), int(round(float(lon) * 1e7)), int(round(float(alt) * 1000)),
                0, 0, 0, 0, 0), sysid, 1, v1)
        if k % 20 == 0:
            if system_time:
                b.add(t + latency_us, m.MAVLink_system_time_message(t, boot_ms), sysid, 1, v1)
            if timesync:
                # request sent by the companion at t (its ns), answered at t + latency, back at t + 2 latency
                tc1 = (t + latency_us - boot_unix_us) * 1000
                b.add(t + 2 * latency_us, m.MAVLink_timesync_message(tc1, t * 1000), sysid, 1, v1)
    b.items.sort(key=lambda it: it[0])
