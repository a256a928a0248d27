"""The agent under load: capture at 10 fps 1280x720 with detection at 320 px, and downloads meanwhile.

Runs ``uavsim agent`` as its own process (as systemd would) with the simulated autopilot on a pty
(armed after 1 s) and a replay camera looping simulator frames at 1280x720; the detector is a real
YOLOv8n ONNX model (random weights: the cost is the same as a trained one) at 320 px on every
frame it can take. After a warm-up it measures for ``--seconds``: frames logged and dropped, the
capture process's resident memory (VmRSS / VmHWM), detector latency, and — in the second half — the
throughput of repeated archive downloads over HTTP while capture continues (drops must stay 0).

    python bench/agent.py [--seconds 30] [--fps 10] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import cv2

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from bench._common import write_json  # noqa: E402

TOKEN = "bench-token-0123456789abcdef"


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _get(url: str, timeout: float = 30.0) -> bytes:
    req = urllib.request.Request(url, headers={"Authorization": f"Bearer {TOKEN}"})
    with urllib.request.urlopen(req, timeout=timeout) as r:
        return r.read()


def _rss_mb(pid: int) -> tuple[float, float]:
    fields = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        k, _, v = line.partition(":")
        fields[k] = v.strip()
    return int(fields["VmRSS"].split()[0]) / 1024, int(fields["VmHWM"].split()[0]) / 1024


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--fps", type=float, default=10.0)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()

    import torch

    from export.onnx_export import export_onnx
    from export.yolo import YOLOv8
    from sim.world import make_world
    from telemetry.camera import Camera
    from telemetry.frames import orbit_pose

    work = Path(tempfile.mkdtemp(prefix="uavsim-bench-agent-"))
    frames = work / "frames"
    frames.mkdir()
    camera = Camera.from_fov(1280, 720, 70.0)
    world = make_world(seed=0)
    for k in range(4):
        res = world.render(camera, orbit_pose(15.0, 20.0, -37.0, 15.0 * k), supersample=1)
        cv2.imwrite(str(frames / f"{k:03d}.png"), cv2.cvtColor(res.rgb, cv2.COLOR_RGB2BGR))
    camera.save(work / "camera.json")
    torch.manual_seed(0)
    model = export_onnx(YOLOv8(nc=3, scale="n", names={0: "standing", 1: "kneeling", 2: "prone"}).eval(),
                        work / "model.onnx", imgsz=320)
    token = work / "token"
    token.write_text(TOKEN)
    token.chmod(0o600)
    port = _port()
    cfg = work / "agent.toml"
    cfg.write_text(f"""
[mavlink]
url = "sim"
[camera]
source = "replay:{frames}"
camera_json = "{work / 'camera.json'}"
fps = {args.fps}
[storage]
root = "{work / 'flights'}"
[detector]
model = "{model}"
rate_hz = {args.fps}
imgsz = 320
threads = 1
[processing]
policy = "manual"
[http]
bind = "127.0.0.1:{port}"
token_file = "{token}"
""")
    base = f"http://127.0.0.1:{port}"
    proc = subprocess.Popen([sys.executable, "-m", "agent.cli", "-q", "agent", "--config", str(cfg)],
                            env={**os.environ, "OMP_WAIT_POLICY": "PASSIVE"})
    try:
        status = {}
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                status = json.loads(_get(base + "/api/status", 5))
                if status["state"] == "capturing" and status["counters"]["frames"] >= args.fps * 3:
                    break
            except OSError:
                pass
            time.sleep(0.5)
        else:
            raise SystemExit(f"agent did not start capturing: {status}")
        s0, t0 = status, time.monotonic()
        half = t0 + args.seconds / 2
        while time.monotonic() < half:
            time.sleep(0.5)
        s_mid = json.loads(_get(base + "/api/status"))
        downloaded, t_dl0 = 0, time.monotonic()
        flight = s0["flight"]
        while time.monotonic() < t0 + args.seconds:
            downloaded += len(_get(base + f"/api/flights/{flight}/archive", 120))
        t_dl = time.monotonic() - t_dl0
        s1 = json.loads(_get(base + "/api/status"))
        rss, hwm = _rss_mb(proc.pid)
        elapsed = time.monotonic() - t0
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(30)
    frames_logged = s1["counters"]["frames"] - s0["counters"]["frames"]
    result = {
        "seconds": round(elapsed, 1), "fps_target": args.fps,
        "frames_logged": frames_logged, "fps_logged": round(frames_logged / elapsed, 2),
        "frames_dropped": s1["counters"]["frames_dropped"] - s0["counters"]["frames_dropped"],
        "frames_dropped_while_downloading": s1["counters"]["frames_dropped"] - s_mid["counters"]["frames_dropped"],
        "detector_frames": s1["detector"]["processed"] - s0["detector"]["processed"],
        "detector_latency_ms_median": s1["detector"]["latency_ms_median"],
        "rss_mb": round(rss, 1), "peak_rss_mb": round(hwm, 1),
        "download_mb": round(downloaded / 1e6, 1), "download_mb_per_s": round(downloaded / 1e6 / t_dl, 1),
        "heavy_modules": s1["heavy_modules"], "exit_code": proc.returncode,
        "load_avg_1min_at_end": os.getloadavg()[0],
    }
    for k, v in result.items():
        print(f"{k}: {v}")
    print(f"wrote {write_json('agent', result, args.json)}")


if __name__ == "__main__":
    main()
