"""The daemon end to end: simulated autopilot over a pty and simulated camera, real HTTP, signals.

The agent runs as its own process (as systemd runs it); the simulated autopilot is a further child
process speaking MAVLink over a pseudo-terminal in real time. Tiny frames keep it fast.
"""

import json
import os
import signal
import socket
import subprocess
import sys
import tarfile
import time
import urllib.error
import urllib.request
from pathlib import Path

TOKEN = "e2e-token-0123456789abcdef"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start_agent(tmp_path: Path, extra: str = "", model: str = ""):
    port = _free_port()
    token = tmp_path / "token"
    token.write_text(TOKEN)
    token.chmod(0o600)
    cfg = tmp_path / "agent.toml"
    cfg.write_text(f"""
[mavlink]
url = "sim"
[camera]
source = "sim"
fps = 5
[storage]
root = "{tmp_path / 'flights'}"
sync_interval_s = 0.5
[detector]
model = "{model}"
rate_hz = 2
imgsz = 160
[processing]
policy = "manual"
[http]
bind = "127.0.0.1:{port}"
token_file = "{token}"
[sim]
width = 96
height = 72
arm_after_s = 1.0
{extra}
""")
    proc = subprocess.Popen([sys.executable, "-m", "agent.cli", "agent", "--config", str(cfg)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return proc, f"http://127.0.0.1:{port}"


def _get(url, token=TOKEN, headers=None, timeout=10):
    h = dict(headers or {})
    if token:
        h["Authorization"] = f"Bearer {token}"
    with urllib.request.urlopen(urllib.request.Request(url, headers=h), timeout=timeout) as r:
        return r.status, r.read()


def _wait_status(base, predicate, timeout_s=60.0, proc=None):
    deadline = time.monotonic() + timeout_s
    last = None
    while time.monotonic() < deadline:
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"agent exited early: {proc.stderr.read()[-3000:]}")
        try:
            last = json.loads(_get(base + "/api/status")[1])
            if predicate(last):
                return last
        except (urllib.error.URLError, ConnectionError, json.JSONDecodeError):
            pass
        time.sleep(0.3)
    raise AssertionError(f"timed out; last status {last}")


def _stop(proc, sig=signal.SIGTERM):
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _untrained_model(tmp_path) -> str:
    """A real YOLOv8n ONNX file (random weights): detections are noise, the path is real."""
    import torch

    from export.onnx_export import export_onnx
    from export.yolo import YOLOv8

    torch.manual_seed(0)
    model = YOLOv8(nc=3, scale="n", names={0: "standing", 1: "kneeling", 2: "prone"}).eval()
    return str(export_onnx(model, tmp_path / "model.onnx", imgsz=160))


def test_agent_captures_serves_and_stops_cleanly(tmp_path):
    proc, base = _start_agent(tmp_path, model=_untrained_model(tmp_path))
    try:
        st = _wait_status(base, lambda s: s["state"] == "capturing" and s["counters"]["frames"] >= 12
                          and s["detector"]["processed"] >= 3, proc=proc)
        assert st["heavy_modules"] == []  # the capture process never imports torch or pycolmap
        assert st["link_connected"] and st["armed"]
        flight = st["flight"]
        # 401 without a token, 404 for escapes, archive and Range with it (curl, as a ground station would)
        r = subprocess.run(["curl", "-s", "-o", "/dev/null", "-w", "%{http_code}", base + "/api/flights"],
                           capture_output=True, text=True)
        assert r.stdout == "401"
        r = subprocess.run(["curl", "-s", "-o", "/dev/null", "-w", "%{http_code}", "-H",
                            f"Authorization: Bearer {TOKEN}", "--path-as-is",
                            base + f"/api/flights/{flight}/files/../../token"], capture_output=True, text=True)
        assert r.stdout == "404"
        archive = tmp_path / "dl.tar"
        r = subprocess.run(["curl", "-sf", "-H", f"Authorization: Bearer {TOKEN}", "-o", str(archive),
                            base + f"/api/flights/{flight}/archive"], capture_output=True, text=True)
        assert r.returncode == 0
        with tarfile.open(archive) as tar:
            names = tar.getnames()
        assert f"{flight}/frames/000000.jpg" in names and f"{flight}/telemetry.tlog" in names
        url = base + f"/api/flights/{flight}/files/frames/000001.jpg"
        full = _get(url)[1]
        part = tmp_path / "part.jpg"
        part.write_bytes(full[:700])
        r = subprocess.run(["curl", "-sf", "-C", "-", "-H", f"Authorization: Bearer {TOKEN}", "-o", str(part), url],
                           capture_output=True, text=True)
        assert r.returncode == 0 and part.read_bytes() == full
    finally:
        _stop(proc)
    assert proc.returncode == 0, proc.stderr.read()[-2000:]
    from telemetry.flightlog import read_flight

    rec = read_flight(tmp_path / "flights" / flight)
    assert len(rec.frames) >= 12
    assert rec.tlog.records and not rec.tlog.truncated_tail
    lines = (tmp_path / "flights" / flight / "detections.jsonl").read_text().splitlines()
    assert len(lines) >= 3
    frame_names = {name for name, _ in rec.frames}
    for line in lines:
        d = json.loads(line)
        assert d["frame"] in frame_names and isinstance(d["detections"], list) and d["latency_ms"] > 0


def test_kill_9_mid_capture_leaves_a_replayable_flight(tmp_path):
    proc, base = _start_agent(tmp_path)
    try:
        st = _wait_status(base, lambda s: s["state"] == "capturing" and s["counters"]["frames"] >= 8, proc=proc)
        time.sleep(1.0)  # past a sync
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
    finally:
        _stop(proc)
    flight = tmp_path / "flights" / st["flight"]
    from agent.replay import ReplayOptions, stage_poses

    summary = stage_poses(flight, ReplayOptions(sfm=False))  # the first stage of `uavsim replay`
    assert summary["telemetry_posed"] >= 5
