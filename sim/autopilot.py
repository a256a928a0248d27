"""A simulated autopilot that speaks real MAVLink 2 bytes (pymavlink, ardupilotmega) over a pty or UDP.

It flies a scripted :class:`Trajectory` (orbit around the scene centre, or a straight line) and, on
its own boot clock (``time_boot_ms``, with a drift against the companion clock), emits HEARTBEAT
1 Hz, SYSTEM_TIME 1 Hz, GLOBAL_POSITION_INT 10 Hz, ATTITUDE 20 Hz and optionally
GIMBAL_DEVICE_ATTITUDE_STATUS 10 Hz; it answers TIMESYNC requests, SET_MESSAGE_INTERVAL (with a
COMMAND_ACK) and REQUEST_DATA_STREAM.

Sensor errors: GPS position and attitude carry first-order Gauss–Markov noise (slowly drifting, as
real receivers do, not white), then the messages quantise (1e-7 deg, mm, float32 radians, whole ms).
Link latency: each message is delivered ``latency_ms`` (uniform in a range) after it is produced,
in order (a serial link cannot reorder). Time is driven from outside (:meth:`SimAutopilot.step`
with the companion clock in unix µs), so a flight can run faster or slower than real time while
the bytes still cross a real pty or socket.
"""

from __future__ import annotations

import heapq
import math
import os
import select
import socket
import tty
from dataclasses import dataclass, field

import numpy as np

from telemetry import mavlink as _mavlink
from telemetry.frames import R_MOUNT_FROM_CAM, cam_from_world_from_attitude, euler_zyx_to_matrix, matrix_to_euler_zyx
from telemetry.frames import mount_from_cam as _mount_from_cam
from telemetry.geodesy import enu_to_geodetic
from telemetry.quat import matrix_to_quat

#: A default geodetic origin for the simulated world (scene centre on the ground, AMSL metres).
DEFAULT_ORIGIN = (47.397742, 8.545594, 488.0)
GRAVITY = 9.80665


# ---- trajectories ------------------------------------------------------------------------------
@dataclass
class VehicleState:
    """True state at one instant: ENU position (m), ENU velocity (m/s), R_ned_from_body (FRD)."""

    position_enu: np.ndarray
    velocity_enu: np.ndarray
    R_ned_from_body: np.ndarray
    #: gimbal attitude relative to the vehicle heading (roll/pitch earth-levelled), or None
    R_gimbal: np.ndarray | None = None


@dataclass
class Orbit:
    """Circle of ``radius_m`` at ``altitude_m`` above ``center``, counter-clockwise, nose to the centre.

    A multicopter holding this orbit pitches its nose down to produce the centripetal acceleration
    (``tilt=True``); the gimbal pitch (if any) keeps the camera on the centre.
    """

    altitude_m: float = 15.0
    radius_m: float = 20.0
    speed_mps: float = 4.0
    start_azimuth_deg: float = 0.0
    center_enu: tuple = (0.0, 0.0, 0.0)
    tilt: bool = True

    def state(self, t_s: float) -> VehicleState:
        c = np.asarray(self.center_enu, dtype=np.float64)
        if self.radius_m <= 0:
            R = euler_zyx_to_matrix(0.0, 0.0, 0.0)
            return VehicleState(c + [0, 0, self.altitude_m], np.zeros(3), R, self._gimbal())
        w = self.speed_mps / self.radius_m
        az = math.radians(self.start_azimuth_deg) + w * t_s
        pos = c + np.array([self.radius_m * math.cos(az), self.radius_m * math.sin(az), self.altitude_m])
        vel = np.array([-self.radius_m * w * math.sin(az), self.radius_m * w * math.cos(az), 0.0])
        to_c = c[:2] - pos[:2]
        yaw_ned = math.atan2(to_c[0], to_c[1])
        pitch = -math.atan(self.speed_mps**2 / (self.radius_m * GRAVITY)) if self.tilt else 0.0
        return VehicleState(pos, vel, euler_zyx_to_matrix(yaw_ned, pitch, 0.0), self._gimbal())

    def look_pitch_deg(self) -> float:
        """Camera pitch (earth frame) that looks at the centre."""
        return -math.degrees(math.atan2(self.altitude_m, max(self.radius_m, 1e-9)))

    def _gimbal(self) -> np.ndarray:
        return euler_zyx_to_matrix(0.0, math.radians(self.look_pitch_deg()), 0.0)


@dataclass
class StraightLine:
    """Constant-velocity flight from ``start_enu`` with heading along the velocity, level attitude."""

    start_enu: tuple = (-30.0, 0.0, 20.0)
    velocity_enu: tuple = (5.0, 0.0, 0.0)
    gimbal_pitch_deg: float = -90.0

    def state(self, t_s: float) -> VehicleState:
        v = np.asarray(self.velocity_enu, dtype=np.float64)
        pos = np.asarray(self.start_enu, dtype=np.float64) + v * t_s
        yaw_ned = math.atan2(v[0], v[1]) if np.linalg.norm(v[:2]) > 1e-9 else 0.0
        R_g = euler_zyx_to_matrix(0.0, math.radians(self.gimbal_pitch_deg), 0.0)
        return VehicleState(pos, v, euler_zyx_to_matrix(yaw_ned, 0.0, 0.0), R_g)


def true_cam_from_world(state: VehicleState, mount_rpy_deg: tuple | None) -> np.ndarray:
    """True OpenCV ``cam_from_world`` (sim world ENU): fixed mount (roll, pitch, yaw deg) or the gimbal."""
    if mount_rpy_deg is not None:
        return cam_from_world_from_attitude(state.position_enu, state.R_ned_from_body, _mount_from_cam(*mount_rpy_deg))
    yaw = matrix_to_euler_zyx(state.R_ned_from_body)[0]
    R_ned_from_gimbal = euler_zyx_to_matrix(yaw, 0.0, 0.0) @ state.R_gimbal
    return cam_from_world_from_attitude(state.position_enu, R_ned_from_gimbal, R_MOUNT_FROM_CAM)


# ---- noise -------------------------------------------------------------------------------------
class GaussMarkov:
    """First-order Gauss–Markov process: stationary std ``sigma``, correlation time ``tau_s``."""

    def __init__(self, sigma, tau_s: float, rng: np.random.Generator, dim: int = 3) -> None:
        self.sigma = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (dim,)).copy()
        self.tau = float(tau_s)
        self.rng = rng
        self.x = self.sigma * rng.standard_normal(dim)
        self.t_s: float | None = None

    def at(self, t_s: float) -> np.ndarray:
        if self.t_s is not None and t_s > self.t_s:
            a = math.exp(-(t_s - self.t_s) / self.tau)
            self.x = a * self.x + self.sigma * math.sqrt(1.0 - a * a) * self.rng.standard_normal(len(self.x))
        self.t_s = t_s if self.t_s is None else max(self.t_s, t_s)
        return self.x.copy()


@dataclass
class NoiseConfig:
    """Sensor and link errors. Zero noise by default; latency is always there."""

    gps_sigma_m: float = 0.0
    gps_vertical_sigma_m: float = 0.0
    gps_tau_s: float = 30.0
    attitude_sigma_deg: float = 0.0
    attitude_tau_s: float = 5.0
    latency_ms: tuple = (15.0, 45.0)

    @classmethod
    def realistic(cls) -> NoiseConfig:
        """A consumer GNSS + IMU/EKF: ~0.5 m horizontal, 0.8 m vertical drift, 0.3 deg attitude."""
        return cls(gps_sigma_m=0.5, gps_vertical_sigma_m=0.8, attitude_sigma_deg=0.3)


@dataclass
class AutopilotConfig:
    system_id: int = 1
    component_id: int = 1
    origin: tuple = DEFAULT_ORIGIN
    #: companion unix µs at which the autopilot booted
    boot_unix_us: int = 0
    #: autopilot clock rate error against the companion clock (parts per million)
    clock_drift_ppm: float = 25.0
    #: send GIMBAL_DEVICE_ATTITUDE_STATUS (from the autopilot component, on its boot clock, as ArduPilot does)
    gimbal: bool = False
    #: False: refuse SET_MESSAGE_INTERVAL (an old firmware), forcing REQUEST_DATA_STREAM
    honour_message_interval: bool = True
    #: armed between these flight times (s after start); None: armed throughout
    armed_window_s: tuple[float, float] | None = None
    rates_hz: dict = field(default_factory=lambda: {"HEARTBEAT": 1.0, "SYSTEM_TIME": 1.0,
                                                     "GLOBAL_POSITION_INT": 10.0, "ATTITUDE": 20.0,
                                                     "GIMBAL_DEVICE_ATTITUDE_STATUS": 10.0})


# ---- transports --------------------------------------------------------------------------------
class PtyTransport:
    """A pty pair: the autopilot holds the master; the companion opens :attr:`device` as a serial port."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        self.device = os.ttyname(self.slave)
        os.set_blocking(self.master, False)

    def url(self, baud: int = 921600) -> str:
        return f"{self.device}:{baud}"

    def write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                n = os.write(self.master, view)
            except BlockingIOError:
                select.select([], [self.master], [], 1.0)
                continue
            view = view[n:]

    def read(self) -> bytes:
        try:
            return os.read(self.master, 65536)
        except (BlockingIOError, OSError):
            return b""

    def wait_readable(self, timeout_s: float) -> bool:
        return bool(select.select([self.master], [], [], timeout_s)[0])

    def close(self) -> None:
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


class UdpTransport:
    """UDP loopback: the autopilot sends each message as one datagram to the companion's ``udpin`` port."""

    def __init__(self, companion_port: int | None = None) -> None:
        if companion_port is None:
            probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            probe.bind(("127.0.0.1", 0))
            companion_port = probe.getsockname()[1]
            probe.close()
        self.peer = ("127.0.0.1", companion_port)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)

    def url(self) -> str:
        return f"udpin:127.0.0.1:{self.peer[1]}"

    def write(self, data: bytes) -> None:
        try:
            self.sock.sendto(data, self.peer)
        except OSError:
            pass  # nobody listening yet: UDP drops it, as a real radio would

    def read(self) -> bytes:
        out = b""
        while True:
            try:
                out += self.sock.recv(65536)
            except (BlockingIOError, OSError):
                return out

    def wait_readable(self, timeout_s: float) -> bool:
        return bool(select.select([self.sock], [], [], timeout_s)[0])

    def close(self) -> None:
        self.sock.close()


# ---- the autopilot -----------------------------------------------------------------------------
class SimAutopilot:
    """See the module docstring. Drive it with :meth:`step` at increasing companion times (unix µs)."""

    def __init__(self, config: AutopilotConfig, trajectory, transport, noise: NoiseConfig | None = None,
                 start_unix_us: int = 0, seed: int = 0) -> None:
        self.config = config
        self.trajectory = trajectory
        self.transport = transport
        self.noise = noise or NoiseConfig()
        self.start_us = int(start_unix_us)
        self.rng = np.random.default_rng(seed)
        self.m = _mavlink.dialect()
        self.mav = _mavlink.new_parser(config.system_id, config.component_id)
        self.rx = _mavlink.new_parser(config.system_id, config.component_id)
        n = self.noise
        self.gps_noise = GaussMarkov([n.gps_sigma_m, n.gps_sigma_m, n.gps_vertical_sigma_m], n.gps_tau_s, self.rng)
        self.att_noise = GaussMarkov(math.radians(n.attitude_sigma_deg), n.attitude_tau_s, self.rng)
        self.periods_us = {k: int(1e6 / v) for k, v in config.rates_hz.items() if v > 0}
        if not config.gimbal:
            self.periods_us.pop("GIMBAL_DEVICE_ATTITUDE_STATUS", None)
        # Stagger the streams so they do not all fire at the same instant.
        self.next_emit = {k: self.start_us + 1000 * (3 + 7 * i) for i, k in enumerate(sorted(self.periods_us))}
        self._outbox: list[tuple[int, int, bytes]] = []  # (deliver_us, seq, bytes), FIFO in time
        self._requests: list[tuple[int, int, object]] = []  # (process_us, seq, msg)
        self._seq = 0
        self._last_delivery = 0
        self.delivered = 0
        self.received: list[str] = []

    # ---- clocks ----
    def boot_us(self, t_unix_us: int) -> float:
        """Autopilot boot clock (µs) at companion time ``t_unix_us`` (drifting)."""
        return (t_unix_us - self.config.boot_unix_us) * (1.0 + self.config.clock_drift_ppm * 1e-6)

    def boot_ms(self, t_unix_us: int) -> int:
        return int(self.boot_us(t_unix_us) // 1000)

    def flight_s(self, t_unix_us: int) -> float:
        return (t_unix_us - self.start_us) / 1e6

    def true_state(self, t_unix_us: int) -> VehicleState:
        return self.trajectory.state(self.flight_s(t_unix_us))

    def _latency_us(self) -> int:
        lo, hi = self.noise.latency_ms
        return int(1000 * self.rng.uniform(lo, hi))

    # ---- scheduling ----
    def next_event_us(self) -> int:
        cands = list(self.next_emit.values())
        if self._outbox:
            cands.append(self._outbox[0][0])
        if self._requests:
            cands.append(self._requests[0][0])
        return min(cands)

    def _queue(self, t_us: int, data: bytes) -> None:
        d = max(self._last_delivery, t_us + self._latency_us())
        self._last_delivery = d
        self._seq += 1
        self.mav.seq = (self.mav.seq + 1) % 256  # pack() does not advance the MAVLink sequence number
        heapq.heappush(self._outbox, (d, self._seq, data))

    def step(self, t_us: int) -> int:
        """Advance to companion time ``t_us``: produce due messages, deliver due bytes. Messages delivered."""
        while self._requests and self._requests[0][0] <= t_us:
            t_proc, _, msg = heapq.heappop(self._requests)
            self._answer(t_proc, msg)
        for name in sorted(self.next_emit, key=self.next_emit.get):
            while self.next_emit[name] <= t_us:
                t_emit = self.next_emit[name]
                self._emit(name, t_emit)
                self.next_emit[name] = t_emit + self.periods_us[name]
        n = 0
        while self._outbox and self._outbox[0][0] <= t_us:
            _, _, data = heapq.heappop(self._outbox)
            self.transport.write(data)
            n += 1
        self.delivered += n
        return n

    def receive(self, t_us: int, expect: int = 0, wait_s: float = 1.0) -> int:
        """Read what the companion sent (waiting up to ``wait_s`` for ``expect`` messages); queue the answers."""
        n = 0
        deadline = None
        import time as _time

        while True:
            data = self.transport.read()
            if data:
                for msg in self.rx.parse_buffer(data) or []:
                    n += 1
                    self.received.append(msg.get_type())
                    self._seq += 1
                    heapq.heappush(self._requests, (t_us + self._latency_us(), self._seq, msg))
            if n >= expect:
                return n
            deadline = deadline or _time.monotonic() + wait_s
            if _time.monotonic() > deadline:
                return n
            self.transport.wait_readable(0.01)

    # ---- messages ----
    def _answer(self, t_us: int, msg) -> None:
        m = self.m
        typ = msg.get_type()
        if typ == "TIMESYNC" and msg.tc1 == 0:
            reply = m.MAVLink_timesync_message(int(self.boot_us(t_us) * 1000), msg.ts1)
            self._queue(t_us, reply.pack(self.mav))
        elif typ == "COMMAND_LONG" and msg.command == m.MAV_CMD_SET_MESSAGE_INTERVAL:
            ok = self.config.honour_message_interval
            if ok:
                name = m.mavlink_map[int(msg.param1)].msgname if int(msg.param1) in m.mavlink_map else None
                if name and name in self.periods_us and msg.param2 > 0:
                    self.periods_us[name] = int(msg.param2)
            result = m.MAV_RESULT_ACCEPTED if ok else m.MAV_RESULT_UNSUPPORTED
            ack = m.MAVLink_command_ack_message(msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())
            self._queue(t_us, ack.pack(self.mav))
        elif typ == "REQUEST_DATA_STREAM":
            rate = max(int(msg.req_message_rate), 1)
            if msg.req_stream_id == m.MAV_DATA_STREAM_POSITION:
                self.periods_us["GLOBAL_POSITION_INT"] = int(1e6 / rate)
            elif msg.req_stream_id == m.MAV_DATA_STREAM_EXTRA1:
                self.periods_us["ATTITUDE"] = int(1e6 / rate)

    def _emit(self, name: str, t_us: int) -> None:
        m = self.m
        boot_ms = self.boot_ms(t_us)
        if name == "HEARTBEAT":
            window = self.config.armed_window_s
            armed = window is None or window[0] <= self.flight_s(t_us) < window[1]
            mode = m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (m.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
            msg = m.MAVLink_heartbeat_message(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA, mode,
                                              4, m.MAV_STATE_ACTIVE if armed else m.MAV_STATE_STANDBY, 3)
        elif name == "SYSTEM_TIME":
            msg = m.MAVLink_system_time_message(int(t_us), boot_ms)
        elif name == "GLOBAL_POSITION_INT":
            s = self.true_state(t_us)
            p = s.position_enu + self.gps_noise.at(self.flight_s(t_us))
            lat, lon, alt = enu_to_geodetic(p, self.config.origin)
            home_alt = self.config.origin[2]
            v = s.velocity_enu
            yaw = matrix_to_euler_zyx(s.R_ned_from_body)[0]
            msg = m.MAVLink_global_position_int_message(
                boot_ms, int(round(float(lat) * 1e7)), int(round(float(lon) * 1e7)), int(round(float(alt) * 1000)),
                int(round((float(alt) - home_alt) * 1000)), int(round(v[1] * 100)), int(round(v[0] * 100)),
                int(round(-v[2] * 100)), int(round(math.degrees(yaw) % 360 * 100)) % 36000)
        elif name == "ATTITUDE":
            s = self.true_state(t_us)
            R = s.R_ned_from_body @ _small_rotation(self.att_noise.at(self.flight_s(t_us)))
            yaw, pitch, roll = matrix_to_euler_zyx(R)
            msg = m.MAVLink_attitude_message(boot_ms, roll, pitch, yaw, 0.0, 0.0, 0.0)
        elif name == "GIMBAL_DEVICE_ATTITUDE_STATUS":
            s = self.true_state(t_us)
            q = matrix_to_quat(s.R_gimbal)
            msg = m.MAVLink_gimbal_device_attitude_status_message(
                0, 0, boot_ms, 0, [float(x) for x in q], 0.0, 0.0, 0.0, 0, 0.0, 0.0, 0)
        else:
            return
        self._queue(t_us, msg.pack(self.mav))


def _small_rotation(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues)."""
    th = float(np.linalg.norm(rotvec))
    if th < 1e-15:
        return np.eye(3)
    k = rotvec / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K


def run_realtime(autopilot: SimAutopilot, stop, clock_us=None, tick_s: float = 0.001) -> None:
    """Drive ``autopilot`` on the wall clock until ``stop`` (a ``threading.Event``) is set.

    For a companion that runs on real time (the daemon's loop): the autopilot thread sends at the
    scheduled instants and answers requests as they arrive, like hardware on the other end of a cable.
    """
    import time as _time

    now = clock_us or (lambda: _time.time_ns() // 1000)
    while not stop.is_set():
        t = now()
        autopilot.step(t)
        autopilot.receive(t, expect=0, wait_s=0.0)
        wait = (autopilot.next_event_us() - now()) / 1e6
        if wait > 0:
            autopilot.transport.wait_readable(min(wait, tick_s * 20))
