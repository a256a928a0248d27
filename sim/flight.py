"""``uavsim sim-flight OUT``: a recorded flight from the simulated hardware, through the real logger.

The simulated autopilot (:mod:`sim.autopilot`) sends real MAVLink bytes over a pty (serial) or UDP
loopback to the real :class:`telemetry.link.CompanionLink`, whose every message goes into the real
:class:`telemetry.flightlog.FlightWriter`; the simulated camera (:mod:`sim.camera_device`) renders
the world at the true pose at its capture times. Time is a discrete-event virtual clock (companion
unix µs): the flight runs as fast as rendering allows, yet every byte crosses the real transport
and is stamped on arrival, exactly as on hardware.

Outputs: the flight directory ``OUT/`` (frames/, frames.csv, telemetry.tlog, camera.json, labels/,
classes.txt) and ``OUT.truth.json`` beside it (outside the flight): the simulator's true poses,
see :func:`write_truth`.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


@dataclass
class SimFlightConfig:
    altitude_m: float = 15.0
    radius_m: float = 20.0
    speed_mps: float = 4.0
    frames: int = 60
    fps: float = 2.0
    trajectory: str = "orbit"  # "orbit" | "line"
    dynamic: bool = False
    seed: int = 0
    noise: str = "none"  # "none" | "realistic"
    latency_ms: tuple = (15.0, 45.0)
    transport: str = "pty"  # "pty" | "udp"
    gimbal: bool = False
    width: int = 640
    height: int = 480
    hfov_deg: float = 70.0
    supersample: int = 2
    #: companion unix µs at the start (None: now)
    start_unix_us: int | None = None
    #: telemetry before the first frame (link set-up, time sync), seconds
    warmup_s: float = 2.0
    #: telemetry after the last frame, seconds
    tail_s: float = 1.0
    world: dict = field(default_factory=dict)  # overrides of sim.world.WorldConfig (e.g. texture_size)


class VirtualClock:
    """Companion clock of the simulation: unix µs, advanced by the event loop."""

    def __init__(self, t_us: int) -> None:
        self.t_us = int(t_us)

    def __call__(self) -> int:
        return self.t_us


def advance(autopilot, link, clock: VirtualClock, t_us: int, wait_s: float = 2.0) -> None:
    """One discrete event at companion time ``t_us``: the autopilot sends what is due, the companion
    reads it all (waiting up to ``wait_s`` of real time for the bytes to cross the transport) and
    answers, and the autopilot takes in the answers."""
    clock.t_us = int(t_us)
    n = autopilot.step(clock.t_us)
    sent0 = link.n_sent
    link.poll(expect=n, wait_s=wait_s)
    if link.n_sent > sent0:
        autopilot.receive(clock.t_us, expect=link.n_sent - sent0, wait_s=wait_s)


def truth_path(out: str | Path) -> Path:
    """``OUT.truth.json`` beside the flight directory ``OUT``."""
    out = Path(out)
    return out.with_name(out.name + ".truth.json")


def write_truth(path: Path, origin, camera, entries: list[dict], world_config: dict, scene_t0_us: int,
                extra: dict) -> None:
    """The simulator's truth: like a poses file but world = the SIM world frame (scene centre at
    ``origin``, ENU), ``source`` = "truth", plus the world config and the scene time origin."""
    data = {"kind": "uavsim-sim-truth",
            "origin": {"lat": origin[0], "lon": origin[1], "alt": origin[2]},
            "camera": camera.to_json(),
            "world": world_config,
            "scene_t0_unix_us": int(scene_t0_us),
            **extra,
            "frames": entries}
    path.write_text(json.dumps(data, indent=1) + "\n")


def load_truth(path: str | Path) -> dict:
    """Read ``OUT.truth.json``; ``cam_from_world`` entries as 4x4 float64 arrays."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such truth file") from None
    if data.get("kind") != "uavsim-sim-truth":
        raise ValueError(f"{path}: not a uavsim simulator truth file")
    for f in data["frames"]:
        f["cam_from_world"] = np.asarray(f["cam_from_world"], dtype=np.float64)
    return data


def run_sim_flight(out: str | Path, config: SimFlightConfig | None = None, progress=None) -> dict:
    """Record a simulated flight into ``out`` (must not exist or be empty); returns a summary dict."""
    from sim.autopilot import (
        DEFAULT_ORIGIN,
        AutopilotConfig,
        NoiseConfig,
        Orbit,
        PtyTransport,
        SimAutopilot,
        StraightLine,
        UdpTransport,
        true_cam_from_world,
    )
    from sim.camera_device import CameraDeviceConfig, SimCamera
    from sim.world import WorldConfig, make_world
    from telemetry.camera import Camera, Mount
    from telemetry.flightlog import FlightWriter, WriterConfig
    from telemetry.link import CompanionLink, LinkConfig

    cfg = config or SimFlightConfig()
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise FileExistsError(f"{out}: already exists and is not empty; choose a new flight directory")
    if cfg.frames < 1:
        raise ValueError(f"--frames must be >= 1, got {cfg.frames}")
    if cfg.altitude_m <= 0:
        raise ValueError(f"--altitude must be > 0 m, got {cfg.altitude_m}")
    if cfg.width < 8 or cfg.height < 8:
        raise ValueError(f"image size must be at least 8x8, got {cfg.width}x{cfg.height}")
    start = cfg.start_unix_us if cfg.start_unix_us is not None else time.time_ns() // 1000
    if cfg.trajectory == "orbit":
        traj = Orbit(cfg.altitude_m, cfg.radius_m, cfg.speed_mps)
        body_pitch = math.degrees(math.asin(-traj.state(0.0).R_ned_from_body[2, 0]))
        mount = (0.0, traj.look_pitch_deg() - body_pitch, 0.0)
    elif cfg.trajectory == "line":
        traj = StraightLine(start_enu=(-cfg.speed_mps * cfg.frames / cfg.fps / 2, 0.0, cfg.altitude_m),
                            velocity_enu=(cfg.speed_mps, 0.0, 0.0))
        mount = (0.0, -90.0, 0.0)
    else:
        raise ValueError(f"trajectory must be 'orbit' or 'line', got {cfg.trajectory!r}")
    if cfg.noise == "none":
        noise = NoiseConfig(latency_ms=tuple(cfg.latency_ms))
    elif cfg.noise == "realistic":
        noise = NoiseConfig.realistic()
        noise.latency_ms = tuple(cfg.latency_ms)
    else:
        raise ValueError(f"--noise must be 'none' or 'realistic', got {cfg.noise!r}")

    camera = Camera.from_fov(cfg.width, cfg.height, cfg.hfov_deg, Mount(*mount))
    world_overrides = {"seed": cfg.seed, "dynamic": cfg.dynamic, **cfg.world}
    world = make_world(WorldConfig(**world_overrides))
    transport = PtyTransport() if cfg.transport == "pty" else UdpTransport() if cfg.transport == "udp" else None
    if transport is None:
        raise ValueError(f"transport must be 'pty' or 'udp', got {cfg.transport!r}")
    rng = np.random.default_rng(cfg.seed + 1)
    ap_cfg = AutopilotConfig(origin=DEFAULT_ORIGIN, boot_unix_us=start - int(rng.uniform(30e6, 600e6)),
                             gimbal=cfg.gimbal)
    autopilot = SimAutopilot(ap_cfg, traj, transport, noise, start_unix_us=start, seed=cfg.seed)
    cam_dev = SimCamera(world, camera, CameraDeviceConfig(fps=cfg.fps, supersample=cfg.supersample,
                                                          phase_us=int(cfg.warmup_s * 1e6) + 37_345), start)
    clock = VirtualClock(start)
    writer = FlightWriter(out, camera, WriterConfig(sync_interval_s=1.0), class_names=list(world.class_names),
                          clock=lambda: clock() / 1e6)
    link = CompanionLink(LinkConfig(transport.url(), source_system=ap_cfg.system_id),
                         on_message=lambda t, raw, msg: writer.add_message(t, raw), clock=clock)
    link.open()
    truth: list[dict] = []
    end_us = None
    t0_wall = time.perf_counter()
    try:
        while True:
            cands = [autopilot.next_event_us(), link.next_due_us()]
            if len(truth) < cfg.frames:
                cands.append(cam_dev.next_capture_us())
            if end_us is not None:
                cands.append(end_us)
            t = max(min(cands), clock.t_us)
            advance(autopilot, link, clock, t)
            if len(truth) < cfg.frames and t >= cam_dev.next_capture_us():
                t_cap = cam_dev.next_capture_us()
                T_true = true_cam_from_world(autopilot.true_state(t_cap), None if cfg.gimbal else mount)
                t_cap, res = cam_dev.capture(T_true)
                name = writer.add_frame(res.rgb, t_cap, labels=res.yolo_labels())
                if name is None:
                    raise OSError(f"flight log stopped: {writer.status}")
                truth.append({"frame": name, "t_unix_us": t_cap, "cam_from_world": T_true.tolist(),
                              "t_scene_s": cam_dev.scene_time_s(t_cap), "source": "truth"})
                if progress:
                    progress(len(truth), cfg.frames)
                if len(truth) == cfg.frames:
                    end_us = t + int(cfg.tail_s * 1e6)
            if end_us is not None and t >= end_us:
                break
    finally:
        link.close()
        writer.close()
        transport.close()
    world_json = asdict(world.config)
    write_truth(truth_path(out), ap_cfg.origin, camera, truth, world_json, cam_dev.first_us,
                {"trajectory": cfg.trajectory, "noise": asdict(noise), "gimbal": cfg.gimbal,
                 "autopilot_boot_unix_us": ap_cfg.boot_unix_us, "clock_drift_ppm": ap_cfg.clock_drift_ppm})
    summary = {"out": str(out), "frames": len(truth), "messages": writer.n_messages,
               "wall_s": time.perf_counter() - t0_wall, "flight_s": (clock.t_us - start) / 1e6,
               "transport": cfg.transport, "requests_seen_by_autopilot": len(autopilot.received),
               "truth": str(truth_path(out))}
    log.info("sim-flight %s: %d frames, %d messages, %.1f s flight in %.1f s", out, len(truth),
             writer.n_messages, summary["flight_s"], summary["wall_s"])
    return summary


# ---- command line ------------------------------------------------------------------------------
def register(subparsers) -> None:
    p = subparsers.add_parser("sim-flight", help="record a simulated flight through the real logger")
    p.add_argument("out", type=Path, help="new flight directory (truth goes to OUT.truth.json)")
    p.add_argument("--altitude", type=float, default=15.0, help="metres above ground")
    p.add_argument("--radius", type=float, default=20.0, help="orbit radius, m")
    p.add_argument("--speed", type=float, default=4.0, help="ground speed, m/s")
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--fps", type=float, default=2.0, help="camera frame rate")
    p.add_argument("--trajectory", choices=("orbit", "line"), default="orbit")
    p.add_argument("--dynamic", action="store_true", help="people walk")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--noise", choices=("none", "realistic"), default="none",
                   help="GPS/attitude noise (link latency 15-45 ms is always on)")
    p.add_argument("--transport", choices=("pty", "udp"), default="pty", help="autopilot link")
    p.add_argument("--gimbal", action="store_true", help="camera on a gimbal that reports its attitude")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--hfov", type=float, default=70.0, help="horizontal field of view, deg")
    p.add_argument("--supersample", type=int, default=2)
    p.add_argument("--fast-world", action="store_true", help="small ground texture (quick tests)")
    p.set_defaults(func=run_cli)


def run_cli(args) -> int:
    world = {"texture_size": 512, "texel_m": 0.05} if args.fast_world else {}
    cfg = SimFlightConfig(altitude_m=args.altitude, radius_m=args.radius, speed_mps=args.speed, frames=args.frames,
                          fps=args.fps, trajectory=args.trajectory, dynamic=args.dynamic, seed=args.seed,
                          noise=args.noise, transport=args.transport, gimbal=args.gimbal, width=args.width,
                          height=args.height, hfov_deg=args.hfov, supersample=args.supersample, world=world)

    def progress(k, n):
        if k == n or k % 10 == 0:
            log.info("frame %d/%d", k, n)

    s = run_sim_flight(args.out, cfg, progress)
    print(f"{s['out']}: {s['frames']} frames, {s['messages']} MAVLink messages over {s['transport']}, "
          f"{s['flight_s']:.1f} s flight in {s['wall_s']:.1f} s; truth: {s['truth']}")
    return 0


def sim_world_from_flight(flight_origin, truth: dict) -> np.ndarray:
    """4x4 rigid transform from a flight's ENU frame (origin = its first fix, e.g. ``PosesFile.origin``)
    to the simulator's world frame (scene centre on the ground). A flight pose in the sim world:
    ``cam_from_world_sim = cam_from_world_flight @ inv(sim_world_from_flight(...))``."""
    from telemetry.geodesy import enu_to_enu_transform

    o = flight_origin
    t = truth["origin"]
    return enu_to_enu_transform((o.lat, o.lon, o.alt), (t["lat"], t["lon"], t["alt"]))


def pose_errors(poses, truth: dict) -> dict:
    """Errors of a :class:`telemetry.posesfile.PosesFile` against a truth dict (:func:`load_truth`).

    Both are brought into the truth's world frame (the poses file's ENU origin differs: it is the first
    fix). Returns per-frame position error (m, camera centres) and rotation error (deg) and medians.
    """
    from telemetry.frames import camera_center
    from telemetry.quat import rotation_angle_deg

    T_truth_from_est = sim_world_from_flight(poses.origin, truth)
    by_name = {f["frame"]: f for f in truth["frames"]}
    pos_err, rot_err, unposed = [], [], 0
    for e in poses.frames:
        if e.frame not in by_name:
            continue
        if not e.posed:
            unposed += 1
            continue
        T_est = np.asarray(e.cam_from_world) @ np.linalg.inv(T_truth_from_est)
        T_true = by_name[e.frame]["cam_from_world"]
        pos_err.append(float(np.linalg.norm(camera_center(T_est) - camera_center(T_true))))
        rot_err.append(rotation_angle_deg(T_est[:3, :3], T_true[:3, :3]))
    arr_p, arr_r = np.array(pos_err), np.array(rot_err)
    return {"n": len(pos_err), "unposed": unposed,
            "pos_median_m": float(np.median(arr_p)) if len(arr_p) else float("nan"),
            "pos_p95_m": float(np.percentile(arr_p, 95)) if len(arr_p) else float("nan"),
            "rot_median_deg": float(np.median(arr_r)) if len(arr_r) else float("nan"),
            "rot_p95_deg": float(np.percentile(arr_r, 95)) if len(arr_r) else float("nan"),
            "pos_err_m": pos_err, "rot_err_deg": rot_err}
