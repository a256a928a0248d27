"""Telemetry benchmarks: tlog parse rate, pose error at frame time against the simulator's truth,
and frames/s logged at 1280x720 JPEG with no drops. Writes bench/out/telemetry.json.

    python bench/telemetry.py [--quick] [--json OUT]

- parse: a tlog of a 600 s factory flight (real pymavlink frames) parsed with telemetry.mavlink;
  also the full pose-track extraction (time sync + geodesy) rate.
- pose error: `sim-flight` through the real logger over a pty (zero noise, link latency uniform
  15-45 ms; then realistic Gauss–Markov noise), `poses --no-sfm`, errors of camera centre and
  rotation against OUT.truth.json.
- logging: ONE simulator frame rendered at 1280x720 (supersample 1), then logged repeatedly as an
  RGB array (JPEG encoding q90 is part of the measured cost, each frame shifted by one pixel so the
  encoder sees new content) with 30 MAVLink messages/s alongside and fsync every second. First as
  fast as possible with the synchronous writer (max fps), then a capture loop paced at 10 fps
  handing frames to the writer thread (telemetry.logqueue, 16-frame queue): a drop = a frame the
  full queue refused; "written" counts the rows in frames.csv after close.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from bench._common import write_json  # noqa: E402


def bench_parse(duration_s: float) -> dict:
    from telemetry.mavlink import parse_tlog_bytes
    from telemetry.poses import extract_tracks
    from tests.telemetry.tlogfactory import TlogBuilder, factory_flight

    b = TlogBuilder()
    factory_flight(b, duration_s=duration_s)
    data = b.data()
    t0 = time.perf_counter()
    res = parse_tlog_bytes(data)
    parse_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    extract_tracks(res.records)
    tracks_s = time.perf_counter() - t0
    n = len(res.records)
    return {"messages": n, "bytes": len(data), "parse_s": parse_s, "parse_msgs_per_s": n / parse_s,
            "tracks_s": tracks_s, "parse_plus_tracks_msgs_per_s": n / (parse_s + tracks_s)}


def bench_pose_error(noise: str, seeds, frames: int, workdir: Path) -> dict:
    from sim.flight import SimFlightConfig, load_truth, pose_errors, run_sim_flight, truth_path
    from telemetry.flightlog import read_flight
    from telemetry.poses import poses_from_telemetry

    pos, rot, unposed, runs = [], [], 0, []
    for seed in seeds:
        out = workdir / f"flight_{noise}_{seed}"
        cfg = SimFlightConfig(frames=frames, fps=4.0, width=160, height=120, supersample=1, seed=seed,
                              noise=noise, latency_ms=(15.0, 45.0),
                              world={"texture_size": 512, "texel_m": 0.05})
        s = run_sim_flight(out, cfg)
        fl = read_flight(out)
        poses, tracks = poses_from_telemetry(fl.tlog.records, fl.frames, fl.camera)
        e = pose_errors(poses, load_truth(truth_path(out)))
        pos += e["pos_err_m"]
        rot += e["rot_err_deg"]
        unposed += e["unposed"]
        runs.append({"seed": seed, "time_source": tracks.time_source, "pos_median_m": e["pos_median_m"],
                     "rot_median_deg": e["rot_median_deg"], "flight_s": s["flight_s"]})
    p, r = np.array(pos), np.array(rot)
    return {"noise": noise, "frames": len(p), "unposed": unposed,
            "pos_median_m": float(np.median(p)), "pos_p95_m": float(np.percentile(p, 95)),
            "pos_rms_m": float(np.sqrt(np.mean(p**2))),
            "rot_median_deg": float(np.median(r)), "rot_p95_deg": float(np.percentile(r, 95)), "runs": runs}


def bench_logging(n_fast: int, n_paced: int, workdir: Path) -> dict:
    from sim.world import make_world
    from telemetry.camera import Camera
    from telemetry.flightlog import FlightWriter
    from telemetry.frames import orbit_pose
    from telemetry.logqueue import QueuedFlightWriter
    from tests.telemetry.tlogfactory import TlogBuilder, factory_flight

    camera = Camera.from_fov(1280, 720, 70.0)
    world = make_world(seed=0, texture_size=1024, texel_m=0.05)
    rgb = world.render(camera, orbit_pose(15, 20, -50, 0), supersample=1).rgb
    b = TlogBuilder()
    factory_flight(b, duration_s=60.0)
    msgs = b.items
    out = {}
    for mode, n in (("max", n_fast), ("paced_10fps", n_paced)):
        root = workdir / f"log_{mode}"
        # max: the synchronous writer's throughput; paced: the capture loop with the writer thread
        w = FlightWriter(root, camera) if mode == "max" else QueuedFlightWriter(FlightWriter(root, camera))
        times, drops, mi = [], 0, 0
        t_start = time.perf_counter()
        for k in range(n):
            slot_start = t_start + k * 0.1
            if mode == "paced_10fps":
                delay = slot_start - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
            t0 = time.perf_counter()
            for _ in range(3):  # 30 messages/s at 10 fps
                w.add_message(msgs[mi % len(msgs)][0], msgs[mi % len(msgs)][1])
                mi += 1
            ok = w.add_frame(np.roll(rgb, k, axis=1), 1_750_000_000_000_000 + k * 100_000)
            times.append(time.perf_counter() - t0)
            drops += not ok
        w.close()
        total = time.perf_counter() - t_start
        written = len((root / "frames.csv").read_text().splitlines()) - 1
        size = sum(f.stat().st_size for f in (root / "frames").iterdir())
        out[mode] = {"frames": n, "wall_s": total, "fps": n / total,
                     "per_frame_ms_median": 1000 * float(np.median(times)),
                     "per_frame_ms_max": 1000 * float(np.max(times)), "drops": drops, "written": written,
                     "mean_jpeg_kb": size / n / 1024, "status": w.status}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer seeds and frames")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    import os

    load = os.getloadavg()
    work = Path(tempfile.mkdtemp(prefix="bench_telemetry_"))
    try:
        parse = bench_parse(120.0 if args.quick else 600.0)
        print(f"parse: {parse['parse_msgs_per_s']:.0f} msg/s ({parse['messages']} msgs); with time sync + tracks: "
              f"{parse['parse_plus_tracks_msgs_per_s']:.0f} msg/s")
        seeds = [0, 1] if args.quick else [0, 1, 2, 3]
        frames = 20 if args.quick else 40
        zero = bench_pose_error("none", seeds, frames, work)
        print(f"pose error, zero noise, latency 15-45 ms: median {100 * zero['pos_median_m']:.2f} cm / "
              f"{zero['rot_median_deg']:.4f} deg "
              f"(p95 {100 * zero['pos_p95_m']:.2f} cm / {zero['rot_p95_deg']:.4f} deg), "
              f"{zero['frames']} frames, {zero['unposed']} unposed")
        real = bench_pose_error("realistic", seeds, frames, work)
        print(f"pose error, realistic noise (GPS 0.5/0.5/0.8 m, att 0.3 deg Gauss-Markov): median "
              f"{real['pos_median_m']:.3f} m, RMS {real['pos_rms_m']:.3f} m / {real['rot_median_deg']:.3f} deg")
        logging_ = bench_logging(30 if args.quick else 60, 50 if args.quick else 100, work)
        for mode, r in logging_.items():
            print(f"logging 1280x720 JPEG {mode}: {r['fps']:.1f} fps, median {r['per_frame_ms_median']:.1f} ms, "
                  f"max {r['per_frame_ms_max']:.1f} ms, drops {r['drops']}/{r['frames']}, written {r['written']}")
        path = write_json("telemetry", {"loadavg_at_start": load, "loadavg_at_end": os.getloadavg(),
                                        "parse": parse, "pose_zero_noise": zero, "pose_realistic": real,
                                        "logging_1280x720": logging_}, args.json)
        print(f"wrote {path}")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
