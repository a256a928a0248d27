"""The on-board agent (``uavsim agent``): capture while armed, process on the ground, serve logs.

States::

    idle ──armed──▶ capturing ──disarmed──▶ processing ──done──▶ idle (new model swapped in if better)
                        ▲                       │
                        └──────armed────────────┘  (processing is paused, capture starts at once)

- capturing: every camera frame and every MAVLink message go into a new recorded flight
  (:class:`telemetry.logqueue.QueuedFlightWriter`: a writer thread, append-only, fsynced every
  ``storage.sync_interval_s``); the ONNX detector runs on frames at ``detector.rate_hz`` in its own
  thread and appends one JSON line per processed frame to ``FLIGHT/detections.jsonl``. The last
  few seconds of telemetry before arming are written at the start of the tlog, so time sync and
  the first fix precede the first frame.
- processing: ``uavsim replay`` on the flight in a child process at low CPU priority (``nice``),
  then the new detector is validated against the current one on the flight's held-out real frames
  and swapped in atomically only if it is not worse. Arming again pauses the child (SIGSTOP) so
  capture never competes with it; disarming resumes it (SIGCONT).

This process imports no torch or pycolmap (``/api/status`` lists ``heavy_modules`` to prove it):
heavy work happens in the child. systemd: READY once the link and camera are open, STATUS on every
state change, WATCHDOG from the main loop; SIGTERM closes the flight cleanly.
"""

from __future__ import annotations

import collections
import json
import logging
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from agent.config import AgentConfig
from agent.sdnotify import Notifier, watchdog_interval_s

log = logging.getLogger(__name__)

HEAVY_MODULES = ("torch", "pycolmap")
PREARM_BUFFER_S = 5.0


def _disk_usage_bytes(root: Path) -> int:
    total = 0
    for dirpath, _, files in os.walk(root):
        for f in files:
            try:
                total += os.lstat(os.path.join(dirpath, f)).st_size
            except OSError:
                pass
    return total


class DetectionWorker:
    """Runs the ONNX detector on the latest submitted frame; never blocks capture.

    Frames arrive through a one-slot mailbox: if the detector is still busy, the older pending frame
    is replaced (detection runs at its own pace, logging does not wait). Results are appended to
    ``detections.jsonl`` of the current flight.
    """

    def __init__(self, model_path: str, conf: float, iou: float, imgsz: int, threads: int):
        from export.infer import Detector  # onnxruntime only, no torch

        self.detector = Detector(model_path, threads=threads, imgsz=imgsz)
        self.conf, self.iou = conf, iou
        self._slot: queue.Queue = queue.Queue(maxsize=1)
        self._out = None
        self._lock = threading.Lock()
        self.latency_ms: collections.deque = collections.deque(maxlen=200)
        self.processed = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="detector", daemon=True)
        self._thread.start()

    def set_output(self, path: Path | None) -> None:
        with self._lock:
            if self._out is not None:
                self._out.close()
            self._out = open(path, "a") if path is not None else None

    def submit(self, frame_name: str, t_unix_us: int, rgb) -> None:
        try:
            self._slot.get_nowait()
        except queue.Empty:
            pass
        try:
            self._slot.put_nowait((frame_name, t_unix_us, rgb))
        except queue.Full:
            pass

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                name, t_us, rgb = self._slot.get(timeout=0.2)
            except queue.Empty:
                continue
            t0 = time.perf_counter()
            dets = self.detector.detect(rgb, conf=self.conf, iou=self.iou)
            ms = 1000 * (time.perf_counter() - t0)
            self.latency_ms.append(ms)
            self.processed += 1
            line = json.dumps({"frame": name, "t_unix_us": t_us, "latency_ms": round(ms, 2),
                               "detections": [d.to_dict() for d in dets]})
            with self._lock:
                if self._out is not None:
                    self._out.write(line + "\n")
                    self._out.flush()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self.set_output(None)


class Agent:
    def __init__(self, config: AgentConfig, notifier: Notifier | None = None):
        self.config = config
        self.notifier = notifier or Notifier()
        self.state = "starting"
        self.flight_dir: Path | None = None
        self.writer = None
        self.link = None
        self.frames = None
        self.hardware = None
        self.detector: DetectionWorker | None = None
        self.server = None
        self.processing: subprocess.Popen | None = None
        self.processing_flight: Path | None = None
        self.armed = False
        self.counters = {"flights": 0, "frames": 0, "frames_dropped": 0, "messages": 0}
        self.last_error: str | None = None
        self._stop = threading.Event()
        self._prearm: collections.deque = collections.deque()
        self._frame_q: queue.Queue = queue.Queue(maxsize=64)
        self._camera_thread: threading.Thread | None = None
        self._last_detect_us = 0
        self._flight_frames = 0
        self._blocked = False  # quota reached: do not retry until the next disarm
        self._lock = threading.Lock()
        self._requests: queue.Queue = queue.Queue()  # flights asked for over the API, processed when idle

    # ---- status ----------------------------------------------------------------------------
    def status(self) -> dict:
        with self._lock:
            det = self.detector
            return {
                "state": self.state, "armed": self.armed,
                "flight": None if self.flight_dir is None else self.flight_dir.name,
                "writer_status": None if self.writer is None else self.writer.status,
                "link_connected": bool(self.link is not None and self.link.connected),
                "detector": None if det is None else {
                    "processed": det.processed,
                    "latency_ms_median": (sorted(det.latency_ms)[len(det.latency_ms) // 2]
                                          if det.latency_ms else None)},
                "processing": None if self.processing is None else str(self.processing_flight),
                "processing_queue": [f.name for f in list(self._requests.queue)],
                "counters": dict(self.counters), "last_error": self.last_error,
                "heavy_modules": [m for m in HEAVY_MODULES if m in sys.modules],
            }

    def _set_state(self, state: str, detail: str = "") -> None:
        self.state = state
        log.info("state: %s %s", state, detail)
        self.notifier.status(f"{state} {detail}".strip())

    # ---- set-up ----------------------------------------------------------------------------
    def _camera_model(self):
        from telemetry.camera import Camera

        camera = getattr(self.frames, "camera", None)  # the simulated camera knows its intrinsics
        return camera if camera is not None else Camera.load(self.config.camera.camera_json)

    def open(self) -> None:
        from telemetry.link import CompanionLink, LinkConfig

        cfg = self.config
        root = Path(cfg.storage.root)
        root.mkdir(parents=True, exist_ok=True)
        url = cfg.mavlink.url
        if url == "sim" or cfg.camera.source == "sim":
            from sim.hardware import SimHardware, SimHardwareConfig

            s = cfg.sim
            self.hardware = SimHardware(SimHardwareConfig(seed=s.seed, altitude_m=s.altitude_m, radius_m=s.radius_m,
                                                          width=s.width, height=s.height,
                                                          arm_after_s=s.arm_after_s, disarm_after_s=s.disarm_after_s))
            sim_url = self.hardware.start()
            if url == "sim":
                url = sim_url
        streams = {"GLOBAL_POSITION_INT": cfg.mavlink.position_hz, "ATTITUDE": cfg.mavlink.attitude_hz,
                   "SYSTEM_TIME": 1.0}
        self.link = CompanionLink(LinkConfig(url, heartbeat_s=1.0 / cfg.mavlink.heartbeat_hz, streams=streams),
                                  on_message=self._on_message)
        self.link.open()
        if cfg.camera.source == "sim":
            self.frames = self.hardware.frame_source(cfg.camera.fps)
        else:
            from agent.camera_source import open_source

            self.frames = open_source(cfg.camera.source, cfg.camera.fps)
        self._camera_model()  # fail early on a bad camera.json
        model = cfg.detector.model
        if model and Path(model).is_file():
            self.detector = DetectionWorker(model, cfg.detector.conf, cfg.detector.iou, cfg.detector.imgsz,
                                            cfg.detector.threads)
        else:
            log.warning("no detector model at %r: in-flight detection off", model)
        if cfg.http.enabled:
            from agent.logserver import LogServer, load_token

            host, _, port = cfg.http.bind.rpartition(":")
            self.server = LogServer(root, load_token(cfg.http.token_file), status=self.status,
                                    request_processing=self.request_processing)
            self.http_port = self.server.start_in_thread(host, int(port))
        self._camera_thread = threading.Thread(target=self._camera_loop, name="camera", daemon=True)
        self._camera_thread.start()
        self._set_state("idle")
        self.notifier.ready("idle")

    # ---- telemetry -------------------------------------------------------------------------
    def _on_message(self, t_us: int, raw: bytes, msg) -> None:
        from telemetry import mavlink as _mavlink

        if _mavlink.is_autopilot_heartbeat(msg):
            m = _mavlink.dialect()
            self.armed = bool(msg.base_mode & m.MAV_MODE_FLAG_SAFETY_ARMED)
        if self.writer is not None:
            if self.writer.add_message(t_us, raw):
                self.counters["messages"] += 1
        else:
            self._prearm.append((t_us, raw))
            while self._prearm and self._prearm[0][0] < t_us - PREARM_BUFFER_S * 1e6:
                self._prearm.popleft()

    # ---- camera ----------------------------------------------------------------------------
    def _camera_loop(self) -> None:
        while not self._stop.is_set():
            try:
                item = self.frames.read()
            except Exception as exc:  # noqa: BLE001 - a camera driver error must not kill capture
                log.error("camera read failed: %s", exc)
                self.last_error = f"camera: {exc}"
                time.sleep(0.5)
                continue
            if item is None:
                if self._stop.is_set():
                    return
                time.sleep(0.05)
                continue
            try:
                self._frame_q.put_nowait(item)
            except queue.Full:
                self.counters["frames_dropped"] += 1

    def _handle_frame(self, t_us: int, rgb) -> None:
        if self.writer is None:
            return
        if not self.writer.add_frame(rgb, t_us):
            self.counters["frames_dropped"] += 1
            return
        name = f"{self._flight_frames:06d}.jpg"  # the writer names frames by arrival order
        self._flight_frames += 1
        self.counters["frames"] += 1
        period = 1e6 / self.config.detector.rate_hz
        if self.detector is not None and t_us - self._last_detect_us >= period:
            self._last_detect_us = t_us
            self.detector.submit(name, t_us, rgb)

    # ---- flights ---------------------------------------------------------------------------
    def _start_capture(self) -> None:
        from telemetry.flightlog import FlightWriter, WriterConfig
        from telemetry.logqueue import QueuedFlightWriter

        root = Path(self.config.storage.root)
        used = _disk_usage_bytes(root)
        quota = self.config.storage.quota_gib * 2**30
        if used >= quota:
            self.last_error = f"storage quota reached ({used / 2**30:.1f} GiB of {self.config.storage.quota_gib})"
            log.error(self.last_error)
            self._set_state("idle", "(quota reached, not logging)")
            self._blocked = True
            return
        self._pause_processing()
        name = time.strftime("flight_%Y%m%d_%H%M%S", time.gmtime())
        self.flight_dir = root / name
        k = 1
        while self.flight_dir.exists():
            self.flight_dir = root / f"{name}_{k}"
            k += 1
        writer = FlightWriter(self.flight_dir, self._camera_model(),
                              WriterConfig(sync_interval_s=self.config.storage.sync_interval_s,
                                           max_bytes=int(quota - used),
                                           jpeg_quality=self.config.camera.jpeg_quality))
        self.writer = QueuedFlightWriter(writer)
        self._flight_frames = 0
        for t_us, raw in self._prearm:
            self.writer.add_message(t_us, raw)
        self._prearm.clear()
        if self.detector is not None:
            self.detector.set_output(self.flight_dir / "detections.jsonl")
        self.counters["flights"] += 1
        while not self._frame_q.empty():  # frames from before arming are not part of the flight
            self._frame_q.get_nowait()
        self._set_state("capturing", self.flight_dir.name)

    def _stop_capture(self) -> Path | None:
        flight = self.flight_dir
        if self.writer is not None:
            while not self._frame_q.empty():
                self._handle_frame(*self._frame_q.get_nowait())
            self.counters["frames_dropped"] += self.writer.dropped_frames
            self.writer.close()
            self.writer = None
        if self.detector is not None:
            self.detector.set_output(None)
        self.flight_dir = None
        log.info("flight %s closed", flight)
        return flight

    # ---- processing ------------------------------------------------------------------------
    def request_processing(self, flight: Path) -> tuple[int, dict]:
        """Queue ``flight`` for processing (called from the HTTP thread); (HTTP status, JSON body).

        Accepted under the "on_disarm" and "manual" policies; the flight runs once the vehicle is disarmed
        and no other processing runs. A flight still being recorded, or one without frames, is refused.
        """
        if self.config.processing.policy == "never":
            return 409, {"error": "processing is disabled (processing.policy = never)"}
        if self.flight_dir is not None and flight.resolve() == self.flight_dir.resolve():
            return 409, {"error": f"{flight.name} is being recorded"}
        if not (flight / "frames.csv").is_file():
            return 409, {"error": f"{flight.name} is not a recorded flight (no frames.csv)"}
        queued = [f.name for f in list(self._requests.queue)]
        if flight.name in queued:
            return 200, {"queued": flight.name, "position": queued.index(flight.name)}
        self._requests.put(flight)
        log.info("processing of %s requested", flight.name)
        return 202, {"queued": flight.name, "position": self._requests.qsize() - 1}

    def _start_requested(self) -> None:
        """Start the next requested flight when nothing else needs the vehicle's CPU."""
        if self.armed or self.writer is not None or self.processing is not None or self._requests.empty():
            return
        self._start_processing(self._requests.get_nowait(), requested=True)

    def _start_processing(self, flight: Path, requested: bool = False) -> None:
        if not requested and self.config.processing.policy != "on_disarm":
            self._set_state("idle")
            return
        cmd = [sys.executable, "-m", "agent.processing", str(flight), "--current", self.config.detector.model,
               "--fit-budget-s", str(self.config.processing.fit_budget_s),
               "--base", self.config.processing.base_detector]
        if self.config.processing.quick:
            cmd.append("--quick")
        nice = self.config.processing.nice
        self.processing = subprocess.Popen(cmd, preexec_fn=lambda: (os.setsid(), os.nice(nice)),
                                           stdout=subprocess.DEVNULL, stderr=open(flight / "processing.log", "a"))
        self.processing_flight = flight
        self._set_state("processing", flight.name)

    def _pause_processing(self) -> None:
        if self.processing is not None and self.processing.poll() is None:
            os.killpg(self.processing.pid, signal.SIGSTOP)
            log.info("processing paused for capture")

    def _resume_processing(self) -> None:
        if self.processing is not None and self.processing.poll() is None:
            os.killpg(self.processing.pid, signal.SIGCONT)
            self._set_state("processing", self.processing_flight.name)

    def _check_processing(self) -> None:
        if self.processing is None or self.processing.poll() is None:
            return
        rc = self.processing.returncode
        flight = self.processing_flight
        self.processing = None
        decision_path = flight / "derived" / "model_decision.json"
        if rc == 0 and decision_path.is_file():
            decision = json.loads(decision_path.read_text())
            if decision.get("swap"):
                self._swap_model(Path(decision["model"]))
            log.info("processing of %s done: %s", flight.name, decision.get("reason"))
        else:
            self.last_error = f"processing of {flight.name} failed (exit {rc}); see processing.log"
            log.error(self.last_error)
        self._set_state("idle")

    def _swap_model(self, new_model: Path) -> None:
        """Atomically replace the current model file and reload the detector."""
        cfg = self.config.detector
        target = Path(cfg.model)
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.with_name(target.name + ".new")
        tmp.write_bytes(new_model.read_bytes())
        os.replace(tmp, target)
        if self.detector is not None:
            self.detector.close()
        self.detector = DetectionWorker(str(target), cfg.conf, cfg.iou, cfg.imgsz, cfg.threads)
        log.info("new detector swapped in from %s", new_model)

    # ---- main loop -------------------------------------------------------------------------
    def run(self) -> int:
        self.open()
        wd = watchdog_interval_s()
        next_wd = time.monotonic()
        try:
            while not self._stop.is_set():
                self.link.poll(wait_s=0.0)
                try:
                    t_us, rgb = self._frame_q.get(timeout=0.01)
                    self._handle_frame(t_us, rgb)
                except queue.Empty:
                    pass
                if self.armed and self.writer is None and not self._blocked:
                    self._start_capture()
                elif not self.armed:
                    self._blocked = False
                    if self.writer is not None:
                        self._start_processing(self._stop_capture())
                    elif self.processing is not None and self.state != "processing":
                        self._resume_processing()
                if self.writer is not None and not self.writer.writer.ok:
                    self.last_error = f"flight log stopped: {self.writer.status}"
                self._check_processing()
                self._start_requested()
                if wd is not None and time.monotonic() >= next_wd:
                    self.notifier.watchdog()
                    next_wd = time.monotonic() + wd
        finally:
            self.close()
        return 0

    def request_stop(self, *_args) -> None:
        self._stop.set()

    def close(self) -> None:
        self.notifier.stopping()
        self._stop.set()
        if self.frames is not None:
            close = getattr(self.frames, "close", None)
            if close:
                close()
        if self.writer is not None:
            self._stop_capture()
        if self.processing is not None and self.processing.poll() is None:
            os.killpg(self.processing.pid, signal.SIGCONT)
            os.killpg(self.processing.pid, signal.SIGTERM)
        if self.detector is not None:
            self.detector.close()
        if self.link is not None:
            self.link.close()
        if self.server is not None:
            self.server.stop()
        if self.hardware is not None:
            self.hardware.stop()
        log.info("agent stopped")


def register(subparsers) -> None:
    p = subparsers.add_parser("agent", help="the on-board daemon (systemd runs this)")
    p.add_argument("--config", type=Path, default=None, help="TOML configuration file")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help="override a setting")
    p.add_argument("--print-config", action="store_true", help="print the effective configuration and exit")
    p.set_defaults(func=run_cli)


def run_cli(args) -> int:
    from agent.config import load_config, to_toml

    config = load_config(args.config, args.set)
    if args.print_config:
        print(to_toml(config))
        return 0
    agent = Agent(config)
    signal.signal(signal.SIGTERM, agent.request_stop)
    signal.signal(signal.SIGINT, agent.request_stop)
    return agent.run()
