"""Simulated drone hardware for the daemon: an autopilot process on a pty, and a camera.

The agent talks to hardware exactly as on a drone: the autopilot is a separate process (as a
flight controller is a separate board) speaking real MAVLink bytes over a pseudo-terminal in real
time (wall clock), armed during a window of the flight; the camera renders the simulated world at
the vehicle's *true* pose at each capture instant, computed from the same trajectory and start
time. Used by ``uavsim agent`` when ``mavlink.url = "sim"`` / ``camera.source = "sim"``.

Child entry point: ``python -m sim.hardware --start-us T --altitude M --radius M --seed N
--arm S,E`` prints ``PTY /dev/pts/N`` once the link is up and runs until SIGTERM.
"""

from __future__ import annotations

import argparse
import math
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np

from telemetry.camera import Camera, Mount


@dataclass(frozen=True)
class SimHardwareConfig:
    seed: int = 0
    altitude_m: float = 15.0
    radius_m: float = 20.0
    speed_mps: float = 4.0
    width: int = 640
    height: int = 480
    hfov_deg: float = 70.0
    supersample: int = 1
    #: armed from/to these seconds after the start (disarm < 0: stays armed)
    arm_after_s: float = 1.0
    disarm_after_s: float = -1.0


def _orbit(cfg: SimHardwareConfig):
    from sim.autopilot import Orbit

    return Orbit(cfg.altitude_m, cfg.radius_m, cfg.speed_mps)


def camera_mount_deg(cfg: SimHardwareConfig) -> tuple[float, float, float]:
    """Fixed mount (roll, pitch, yaw deg) that looks at the orbit centre from the tilted body."""
    orbit = _orbit(cfg)
    body_pitch = math.degrees(math.asin(-orbit.state(0.0).R_ned_from_body[2, 0]))
    return (0.0, orbit.look_pitch_deg() - body_pitch, 0.0)


def sim_camera(cfg: SimHardwareConfig) -> Camera:
    return Camera.from_fov(cfg.width, cfg.height, cfg.hfov_deg, Mount(*camera_mount_deg(cfg)))


def _die_with_parent() -> None:
    """In the child: get SIGTERM when the parent dies (Linux), so a killed agent leaves no orphan."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


class SimHardware:
    """Starts the autopilot child process; gives the link URL and a camera frame source."""

    def __init__(self, cfg: SimHardwareConfig, start_unix_us: int | None = None):
        self.cfg = cfg
        self.start_us = int(start_unix_us if start_unix_us is not None else time.time_ns() // 1000)
        self.proc: subprocess.Popen | None = None
        self.device: str | None = None

    def start(self, timeout_s: float = 20.0) -> str:
        c = self.cfg
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "sim.hardware", "--start-us", str(self.start_us), "--altitude", str(c.altitude_m),
             "--radius", str(c.radius_m), "--speed", str(c.speed_mps), "--seed", str(c.seed),
             "--arm", f"{c.arm_after_s},{c.disarm_after_s}"],
            stdout=subprocess.PIPE, text=True, preexec_fn=_die_with_parent)
        deadline = time.monotonic() + timeout_s
        line = ""
        while time.monotonic() < deadline:
            line = self.proc.stdout.readline()
            if line.startswith("PTY "):
                self.device = line.split()[1]
                return f"{self.device}:921600"
            if self.proc.poll() is not None:
                break
        self.stop()
        raise RuntimeError(f"simulated autopilot did not start (last output {line!r})")

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        self.proc = None

    def frame_source(self, fps: float):
        return SimFrameSource(self.cfg, self.start_us, fps)


class SimFrameSource:
    """A camera that renders the world at the true pose, free-running at ``fps`` on the wall clock.

    :meth:`read` blocks until the next exposure and returns (t_unix_us, RGB uint8 HxWx3).
    """

    def __init__(self, cfg: SimHardwareConfig, start_unix_us: int, fps: float):
        from sim.autopilot import true_cam_from_world
        from sim.world import make_world

        self.cfg = cfg
        self.camera = sim_camera(cfg)
        self.world = make_world(seed=cfg.seed, texture_size=1024, texel_m=0.1)
        self.orbit = _orbit(cfg)
        self.mount = camera_mount_deg(cfg)
        self.start_us = start_unix_us
        self.period_us = int(1e6 / fps)
        self.next_us = max(start_unix_us, time.time_ns() // 1000)
        self._true = true_cam_from_world
        self._closed = threading.Event()

    def read(self):
        while not self._closed.is_set():
            now = time.time_ns() // 1000
            if now >= self.next_us:
                break
            self._closed.wait(min((self.next_us - now) / 1e6, 0.05))
        if self._closed.is_set():
            return None
        t = time.time_ns() // 1000
        # Skip exposures that rendering made us miss, like a free-running sensor does.
        self.next_us += self.period_us * max(1, (t - self.next_us) // self.period_us + 1)
        T = self._true(self.orbit.state((t - self.start_us) / 1e6), self.mount)
        res = self.world.render(self.camera, T, t=(t - self.start_us) / 1e6, supersample=self.cfg.supersample)
        return t, res.rgb

    def close(self) -> None:
        self._closed.set()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="simulated autopilot on a pty, in real time")
    ap.add_argument("--start-us", type=int, required=True)
    ap.add_argument("--altitude", type=float, default=15.0)
    ap.add_argument("--radius", type=float, default=20.0)
    ap.add_argument("--speed", type=float, default=4.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--arm", default="1,-1", help="armed from,to seconds after start (to < 0: stays armed)")
    args = ap.parse_args(argv)
    from sim.autopilot import DEFAULT_ORIGIN, AutopilotConfig, NoiseConfig, PtyTransport, SimAutopilot, run_realtime

    a0, a1 = (float(v) for v in args.arm.split(","))
    window = (a0, a1 if a1 >= 0 else math.inf)
    transport = PtyTransport()
    rng = np.random.default_rng(args.seed + 1)
    ap_cfg = AutopilotConfig(origin=DEFAULT_ORIGIN, boot_unix_us=args.start_us - int(rng.uniform(30e6, 600e6)),
                             armed_window_s=window)
    orbit = _orbit(SimHardwareConfig(altitude_m=args.altitude, radius_m=args.radius, speed_mps=args.speed))
    autopilot = SimAutopilot(ap_cfg, orbit, transport, NoiseConfig(), start_unix_us=args.start_us, seed=args.seed)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    print(f"PTY {transport.device}", flush=True)
    try:
        run_realtime(autopilot, stop)
    finally:
        transport.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
