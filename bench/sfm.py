"""SfM pose error against telemetry noise, and seconds per image (issue 4 acceptance).

1. Simulated orbit (15 m altitude, 20 m radius, looking at the centre, N frames, 640x480, 70° hfov)
   with telemetry priors perturbed by first-order Gauss-Markov noise (GPS sigma per axis, attitude
   sigma per axis, tau 60 s) at several noise levels: median rotation / centre error of the refined
   poses against the simulator truth, after one similarity alignment (and its scale) and without
   alignment, next to the telemetry's own errors.
2. Seneca (23 real geotagged photos, 1200 px): import, SfM from EXIF GPS priors alone: registered
   frames, mean reprojection error, centre change from the EXIF positions, seconds per image.

Writes bench/out/sfm.json.

    python bench/sfm.py [--frames 60] [--noise 0.5:1,1:2,2:2] [--seneca DIR] [--skip-sim] [--skip-seneca]
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from bench._common import write_json  # noqa: E402
from telemetry.camera import Camera  # noqa: E402
from telemetry.sfm import SfmOptions, pose_errors, refine_poses  # noqa: E402
from telemetry.sfm_sim import noisy_priors, orbit_truth, render_orbit  # noqa: E402

_HERE = Path(__file__).resolve()
SENECA = next((p / "shared" / "data" / "seneca" for p in _HERE.parents if (p / "shared" / "data" / "seneca").is_dir()),
              Path("/work/shared/data/seneca"))


def _load() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "?"


def _summary(e: dict) -> dict:
    return {k: round(float(v), 5) for k, v in e.items() if k in ("scale", "median_rot_deg", "median_pos_m")}


def bench_sim(work: Path, frames: int, noise: list[tuple[float, float]], seed: int) -> dict:
    t0 = time.perf_counter()
    cached = sorted((work / "orbit").glob("*.png"))
    if len(cached) == frames:  # same deterministic world and orbit: reuse the renders of an earlier run
        images, camera = cached, Camera.from_fov(640, 480, 70.0)
        truth, times = orbit_truth(frames)
    else:
        images, camera, truth, times = render_orbit(work / "orbit", n_frames=frames, width=640, height=480)
    render_s = time.perf_counter() - t0
    rows = []
    for gps, att in noise:
        priors = noisy_priors([p.name for p in images], truth, times, gps, att, seed=seed)
        for p in priors:
            p.attitude_sigma_deg = max(att, 0.1)
        load = _load()
        t0 = time.perf_counter()
        res = refine_poses(images, camera, priors, work / "sfm", SfmOptions(seed=seed))
        sec = time.perf_counter() - t0
        ok = [k for k, f in enumerate(res.frames) if f.source == "sfm"]
        est = [res.frames[k].cam_from_world for k in ok]
        tr = [truth[k] for k in ok]
        tel = [priors[k].cam_from_world for k in ok]
        row = {"gps_sigma_m": gps, "attitude_sigma_deg": att, "registered": len(ok), "frames": frames,
               "seconds": round(sec, 1), "s_per_image": round(sec / frames, 2), "load_before": load,
               "load_after": _load(), "mean_reprojection_px": res.report.get("mean_reprojection_px"),
               "sfm_aligned": _summary(pose_errors(est, tr, True)) if len(ok) >= 3 else None,
               "sfm_raw": _summary(pose_errors(est, tr, False)) if ok else None,
               "telemetry_aligned": _summary(pose_errors(tel, tr, True)) if len(ok) >= 3 else None,
               "telemetry_raw": _summary(pose_errors(tel, tr, False)) if ok else None,
               "stage_seconds": res.report.get("seconds")}
        print(row, flush=True)
        rows.append(row)
    return {"render_s": render_s, "size": [640, 480], "rows": rows}


def bench_seneca(work: Path, src: Path, max_image_size: int) -> dict:
    from telemetry.exif import import_photos
    from telemetry.sfm_flight import refine_flight

    flight = work / "seneca"
    shutil.rmtree(flight, ignore_errors=True)
    imported = import_photos(src, flight)
    load = _load()
    t0 = time.perf_counter()
    res = refine_flight(flight, options=SfmOptions(refine_intrinsics=True, max_image_size=max_image_size))
    sec = time.perf_counter() - t0
    changes = [f.stats.get("position_change_m") for f in res.frames if f.source == "sfm"]
    sig = [f.stats.get("position_change_sigma") for f in res.frames if f.source == "sfm"]
    out = {"frames": len(res.frames), "registered": res.num_refined, "max_image_size": max_image_size,
           "mean_reprojection_px": res.report.get("mean_reprojection_px"),
           "mean_track_length": res.report.get("mean_track_length"), "points": len(res.points_xyz),
           "median_centre_change_m": float(np.median(changes)) if changes else None,
           "max_centre_change_m": float(np.max(changes)) if changes else None,
           "max_centre_change_sigma": float(np.max(sig)) if sig else None,
           "gps_sigma_m": {"horizontal": 3.0, "vertical": 5.0},
           "unregistered": res.report.get("unregistered"), "initial_poses": res.report.get("initial_poses"),
           "mapper_models": res.report.get("mapper_models"), "focal_px_exif": imported["focal_px"],
           "focal_px_refined": res.camera.fx, "seconds": round(sec, 1), "s_per_image": round(sec / len(res.frames), 2),
           "stage_seconds": res.report.get("seconds"), "load_before": load, "load_after": _load()}
    print(out, flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--noise", default="0.5:1,1:2,2:2", help="gps_m:attitude_deg pairs")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--seneca", type=Path, default=SENECA)
    ap.add_argument("--max-image-size", type=int, default=1200)
    ap.add_argument("--skip-sim", action="store_true")
    ap.add_argument("--skip-seneca", action="store_true")
    ap.add_argument("--work", type=Path, default=None, help="scratch folder (default: a temp dir)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    noise = [tuple(float(v) for v in item.split(":")) for item in args.noise.split(",") if item]
    work = args.work or Path(tempfile.mkdtemp(prefix="uavsim_bench_sfm_"))
    payload = {"command": " ".join(sys.argv), "load_start": _load()}
    if not args.skip_sim:
        payload["sim"] = bench_sim(work, args.frames, noise, args.seed)
    if not args.skip_seneca:
        if args.seneca.is_dir():
            payload["seneca"] = bench_seneca(work, args.seneca, args.max_image_size)
        else:
            print(f"no Seneca photos at {args.seneca}; skipped")
    path = write_json("sfm", payload, args.json)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
