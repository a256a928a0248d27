"""Dynamic scenes: held-out PSNR of stock vs extended K-Planes at equal options and wall-clock budget.

The paper's Table III on a simulated Okutama-like flight (fields.dynamic_simscene): the simulator
world with walking people (seed 0), a slightly irregular straight pass at 15 m looking 60 deg down,
``--frames`` frames (paper ~300; default 80 here for one CPU core) at 0.2 s scene time apart,
``--width`` px wide (default 160x120), every other frame (in time) for training and the rest for
validation; poses carry injected telemetry-like noise (GNSS/IMU Gauss–Markov drift + per-frame
jitter, see fields.dynamic_simscene.PoseNoise). Both kinds use the same DynamicFitConfig except
``kind`` and stop at the same training budget (evaluation time not counted). Reports the mean
held-out PSNR / SSIM over all validation frames, PSNR inside person boxes, steps, parameters, MB,
and the pose errors against the simulator's true poses (as given, and as rendered after the learned
pose-drift correction, ``DynamicFitConfig.pose_knot_s``: on by default since session 7 for telemetry
poses, off for SfM-refined ones since session 9; off with ``--set pose_knot_s=null``, forced on SfM poses
with ``--set pose_drift_on_sfm=true``; the air prior likewise, ``DynamicFitConfig.air_prior``, since
session 24: ``--set air_prior=true`` forces it on SfM poses, ``--set lambda_empty=0`` turns it off).
``--sfm``: first refine the noisy telemetry poses with SfM (pycolmap, telemetry priors, every frame,
as ``uavsim poses`` does on a recorded flight; cached as a copy of the flight folder with suffix
``_sfm``): the paper's set-up, whose poses came from COLMAP.

Held-out frames carry their own white pose jitter, which no field can know; ``--align-steps`` (default
150) therefore also reports held-out PSNR after each held-out frame's pose is aligned to the frozen
field on its background pixels (fields.heldout_poses; the BARF / NeRF-- / CamP protocol), next to the
plain number, never instead of it. ``--save-fits DIR`` keeps each kind's checkpoint; ``--load-fits DIR``
evaluates kept checkpoints again (no training; e.g. with other alignment options).

Held-out frames sit between two training instants, so a background painted frame by frame, which the
time planes allow, still passes the held-out test; from higher up it shows. ``--novel-scale`` (default
2: 30 m) therefore also scores each fit of a simulated flight against simulator truth from that many
times the distance, over the ground >= 2 training frames saw, as bench/dynamic_novel.py does (JSON
``stock_novel_psnr``, ``extended_novel_psnr``; bench/RESULTS.md, Table III session 33: on telemetry
poses the two measures rank the kinds oppositely).

    uavsim bench dynamic -- [--budget-s 300] [--frames 80] [--width 160] [--json OUT]
    uavsim bench dynamic -- --kinds kplanes --set features=32   # one option changed for both kinds
    uavsim bench dynamic -- --frames 300 --sfm                   # on SfM-refined poses
    uavsim bench dynamic -- --frames 300 --load-fits DIR --align-steps 300   # re-evaluate kept fits
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from bench._common import OUT_DIR, write_json  # noqa: E402


def parse_setting(text: str) -> tuple[str, object]:
    """``key=value`` -> (key, value), the value parsed as JSON when it parses (``[4,15]``, ``null``,
    ``true``), else kept as text."""
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise SystemExit(f"--set wants KEY=VALUE, got {text!r}")
    try:
        return key, json.loads(value)
    except json.JSONDecodeError:
        return key, value


def load_avg() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def flight_dir(width: int, frames: int, tag: str = "") -> Path:
    """Where the simulated dynamic flight of this size is cached (shared by the dynamic benches)."""
    return OUT_DIR / f"dynamic_flight_{width}px_{frames}f{tag}"


def setup_torch(threads: int | None) -> None:
    """Flush denormals (products of small plane features hit them: 2x slower without) and set threads."""
    import torch

    torch.set_flush_denormal(True)
    if threads:
        torch.set_num_threads(threads)


#: the seed of the bench flights' simulator world, line and pose noise (``prepare``); the views from higher
#: up are rendered in the same world
FLIGHT_SEED = 0


def prepare(flight: Path, frames: int, width: int, seed: int = FLIGHT_SEED, jitter_m: float = 0.05,
            jitter_deg: float = 0.15, drift_scale: float = 1.0, dt_s: float = 0.2) -> None:
    """Render the flight once (cached under bench/out); ``jitter_*``: white per-frame pose noise;
    ``drift_scale`` scales the GNSS/IMU Gauss–Markov drift (0: poses consistent up to the jitter, as
    after SfM); ``dt_s``: scene seconds between frames (the pass covers the same ground in ``frames * dt_s``)."""
    if (flight / "derived" / "poses.json").is_file():
        return
    from fields.dynamic_simscene import LineSpec, PoseNoise, write_line_flight
    from sim.world import make_world
    from telemetry.camera import Camera, Mount

    world = make_world(seed=seed, dynamic=True)
    camera = Camera.from_fov(width, width * 3 // 4, 70.0, Mount(pitch_deg=-60.0))
    base = PoseNoise()
    noise = PoseNoise(gps_sigma_m=base.gps_sigma_m * drift_scale,
                      gps_vertical_sigma_m=base.gps_vertical_sigma_m * drift_scale,
                      attitude_sigma_deg=base.attitude_sigma_deg * drift_scale,
                      seed=seed + 1, jitter_m=jitter_m, jitter_deg=jitter_deg)
    write_line_flight(flight, world, camera, LineSpec(frames=frames, seed=seed, dt_s=dt_s), noise, supersample=2)


def refine_with_sfm(flight: Path) -> Path:
    """A copy of ``flight`` (and its truth file) whose poses SfM refined from the noisy telemetry poses
    as priors; cached. SIFT from the first octave -1 (2x upsampled): 160 px frames have ~240 features each."""
    import shutil

    from telemetry.frames import camera_center
    from telemetry.pose_pipeline import GPS_SIGMA_M
    from telemetry.posesfile import PosesFile
    from telemetry.sfm import Prior, SfmOptions
    from telemetry.sfm_flight import refine_flight

    out = flight.with_name(flight.name + "_sfm")
    if (out / "derived" / "colmap").is_dir():
        return out
    if out.exists():
        shutil.rmtree(out)  # an interrupted run: start over
    shutil.copytree(flight, out)
    truth = flight.with_name(flight.name + ".truth.json")
    if truth.is_file():
        shutil.copy(truth, out.with_name(out.name + ".truth.json"))
    poses = PosesFile.load(flight / "derived" / "poses.json")
    priors = [Prior(e.frame, e.t_unix_us, camera_center(e.cam_from_world), sigma_m=GPS_SIGMA_M,
                    cam_from_world=e.cam_from_world) for e in poses.frames]
    r = refine_flight(out, priors=priors, origin=poses.origin, options=SfmOptions(num_threads=1, sift_first_octave=-1))
    print(f"SfM: {r.num_refined} of {len(priors)} frames refined, mean reprojection "
          f"{r.report.get('mean_reprojection_px')} px, {r.report['seconds']['total']:.0f} s", flush=True)
    return out


def pose_errors(model, dd, indices: list[int], truth_path: Path) -> dict | None:
    """Camera-centre (m) and attitude (deg) errors against the simulator's true poses of the frames
    ``indices``: as given to the fit (telemetry) and as the model renders them (drift-corrected).
    ``*_raw``: median error in the world frame. ``*_varying``: median error after removing the
    frames' mean centre offset and mean rotation offset — the part that changes over the flight and
    makes frames disagree (a common offset only moves the whole scene)."""
    import json

    import numpy as np
    from scipy.spatial.transform import Rotation

    if not truth_path.is_file() or not indices:
        return None
    true = {f["frame"]: np.asarray(f["cam_from_world"]) for f in json.loads(truth_path.read_text())["frames"]}
    t01 = dd.t01()

    def stats(poses, truths):
        dc = np.array([-T[:3, :3].T @ T[:3, 3] + Tt[:3, :3].T @ Tt[:3, 3] for T, Tt in zip(poses, truths, strict=True)])
        # world-frame attitude error of each camera: R_world_cam = dR @ R_world_cam_true
        dr = np.array([Rotation.from_matrix(T[:3, :3].T @ Tt[:3, :3]).as_rotvec() for T, Tt in zip(poses, truths,
                                                                                                  strict=True)])
        return {"centre_raw_m": float(np.median(np.linalg.norm(dc, axis=1))),
                "centre_varying_m": float(np.median(np.linalg.norm(dc - dc.mean(0), axis=1))),
                "rot_raw_deg": float(np.degrees(np.median(np.linalg.norm(dr, axis=1)))),
                "rot_varying_deg": float(np.degrees(np.median(np.linalg.norm(dr - dr.mean(0), axis=1))))}

    truths = [true[dd.data.names[i]] for i in indices]
    given = [dd.data.cam_from_world[i] for i in indices]
    fitted = [model.field_pose(dd.data.cam_from_world[i], float(t01[i])) for i in indices]
    return {"given": stats(given, truths), "fitted": stats(fitted, truths)}


def frame_alignment(model, dd, train_idx: list[int], val_idx: list[int], truth_path: Path) -> dict | None:
    """Misregistration (px) of true ground points between each frame and a render at its pose
    (:mod:`fields.pose_alignment`), for the poses as given and as the model renders them (drift
    knots applied): the world similarity is fitted on the training frames, then applied to the
    training and the held-out frames."""
    import json

    import numpy as np

    from fields.pose_alignment import alignment_report

    if not truth_path.is_file() or not train_idx:
        return None
    true = {f["frame"]: np.asarray(f["cam_from_world"]) for f in json.loads(truth_path.read_text())["frames"]}
    t01 = dd.t01()
    cam = dd.data.camera

    def poses(kind, idx):
        if kind == "given":
            return [dd.data.cam_from_world[i] for i in idx]
        return [model.field_pose(dd.data.cam_from_world[i], float(t01[i])) for i in idx]

    idx = {"train": train_idx, "heldout": val_idx}
    out = {}
    for kind in ("given", "fitted"):
        sets = {name: (poses(kind, ii), [true[dd.data.names[i]] for i in ii]) for name, ii in idx.items()}
        out[kind] = alignment_report(cam, sets["train"], sets)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--budget-s", type=float, default=300.0, help="training seconds per kind")
    ap.add_argument("--frames", type=int, default=80)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--kinds", default="kplanes,kplanes-ext")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: OMP_NUM_THREADS)")
    ap.add_argument("--jitter-m", type=float, default=0.05, help="white per-frame camera-centre noise, m")
    ap.add_argument("--jitter-deg", type=float, default=0.15, help="white per-frame attitude noise, deg")
    ap.add_argument("--drift-scale", type=float, default=1.0,
                    help="scale of the GNSS/IMU drift in the injected pose noise (0: none, SfM-like poses)")
    ap.add_argument("--dt-s", type=float, default=0.2,
                    help="scene seconds between frames (0.2: people walk ~0.5 m between training frames; "
                         "the paper's 30 fps clip: 1/30)")
    ap.add_argument("--flight", type=Path, default=None, help="flight folder (default bench/out/dynamic_...)")
    ap.add_argument("--json", default=None)
    ap.add_argument("--sfm", action="store_true", help="refine the noisy poses with SfM first (cached)")
    ap.add_argument("--save-fits", type=Path, default=None,
                    help="keep each kind's final checkpoint in DIR/KIND/ (default: not kept)")
    ap.add_argument("--load-fits", type=Path, default=None,
                    help="evaluate the checkpoints DIR/KIND/dynamic.pt (from --save-fits) instead of training")
    ap.add_argument("--align-steps", type=int, default=150,
                    help="also report held-out PSNR after aligning each held-out frame's pose to the frozen field "
                         "(fields.heldout_poses; Adam steps over all held-out frames, 0: off)")
    ap.add_argument("--align-set", action="append", default=[], metavar="KEY=VALUE",
                    help="an AlignmentOptions option (batch_rays=4096, lr_m=0.004), repeatable")
    ap.add_argument("--novel-scale", type=float, default=2.0,
                    help="also score each fit from this many times the distance against simulator truth "
                         "(bench/dynamic_novel.py: 2 = 30 m; 0: off)")
    ap.add_argument("--novel-every", type=int, default=5, help="every k-th held-out frame for --novel-scale")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a DynamicFitConfig option for both kinds, value as JSON (features=32, gate=false, "
                         "mask_init_background=null), repeatable")
    args = ap.parse_args()

    import torch

    from fields.dynamic_data import load_dynamic_flight
    from fields.dynamic_training import (
        DynamicFitConfig,
        DynamicFitResult,
        evaluate_dynamic,
        fit_dynamic,
        load_dynamic_checkpoint,
        split,
    )
    from fields.heldout_poses import AlignmentOptions, align_flight_frames

    setup_torch(args.threads)
    overrides = dict(parse_setting(item) for item in args.set)
    align_options = AlignmentOptions(**{"steps": args.align_steps, **dict(parse_setting(i) for i in args.align_set)})
    jitter = (args.jitter_m, args.jitter_deg)
    tag = "" if jitter == (0.05, 0.15) else f"_jit{args.jitter_m:g}m{args.jitter_deg:g}deg"
    tag += "" if args.drift_scale == 1.0 else f"_drift{args.drift_scale:g}"
    tag += "" if args.dt_s == 0.2 else f"_dt{args.dt_s:g}s"
    flight = args.flight or flight_dir(args.width, args.frames, tag)
    t0 = time.perf_counter()
    prepare(flight, args.frames, args.width, seed=FLIGHT_SEED, jitter_m=args.jitter_m, jitter_deg=args.jitter_deg,
            drift_scale=args.drift_scale, dt_s=args.dt_s)
    if args.sfm:
        flight = refine_with_sfm(flight)
        tag += "_sfm"
    dd = load_dynamic_flight(flight)
    train_idx, val_idx = split(dd, 2)
    load_start = load_avg()
    print(f"flight {flight}: {dd.n} frames ({len(train_idx)} train / {len(val_idx)} val), ready in "
          f"{time.perf_counter() - t0:.0f} s; {load_start}", flush=True)
    truth = flight.with_name(flight.name + ".truth.json")
    views = None
    if args.novel_scale > 0 and truth.is_file():
        from bench.dynamic_novel import novel_views, score_novel_views, summary_line
        from sim.world import make_world

        views = novel_views(flight, dd, train_idx, val_idx, make_world(seed=FLIGHT_SEED, dynamic=True),
                            args.novel_scale, args.novel_every)
    results = {}
    for kind in args.kinds.split(","):
        cfg = DynamicFitConfig(kind=kind, budget_s=args.budget_s, iters=10**9, threads=args.threads,
                               checkpoint_every_s=1e9, **overrides)
        if args.load_fits:
            model, ck = load_dynamic_checkpoint(args.load_fits / kind / "dynamic.pt")
            if ck["fit_config"]["budget_s"] != args.budget_s:
                raise SystemExit(f"{args.load_fits / kind}: fitted with --budget-s {ck['fit_config']['budget_s']:g}, "
                                 f"not {args.budget_s:g}")
            r = DynamicFitResult(model, ck["step"], ck["train_s"], ck.get("curve") or [])
        else:
            r = fit_dynamic(dd, cfg, out_dir=args.save_fits / kind if args.save_fits else None, flight=flight)
        t_e = time.perf_counter()
        ev = evaluate_dynamic(r.model, dd, val_idx, out_dir=OUT_DIR / f"dynamic_{kind}{tag}_heldout")
        aligned = None
        if args.align_steps > 0:
            t_a = time.perf_counter()
            poses_aligned, report = align_flight_frames(r.model, dd, val_idx, align_options)
            ev_a = evaluate_dynamic(r.model, dd, val_idx, poses=poses_aligned)
            aligned = {"psnr": ev_a["psnr"], "ssim": ev_a["ssim"], "box_psnr": ev_a["box_psnr"],
                       "bg_psnr": ev_a["bg_psnr"], "box_iou_mean": ev_a["box_iou_mean"],
                       "alignment": {**report, "options": dataclasses.asdict(align_options)},
                       "seconds": round(time.perf_counter() - t_a, 1),
                       "per_frame_psnr": [round(f["psnr"], 3) for f in ev_a["frames"]]}
        novel = None
        if views is not None:
            t_n = time.perf_counter()
            novel_mean, novel_rows, _ = score_novel_views(r.model, dd, train_idx, views)
            novel = {**novel_mean, "seconds": round(time.perf_counter() - t_n, 1), "frames": novel_rows}
        n = r.model.param_count()
        poses = {"train": pose_errors(r.model, dd, train_idx, truth),
                 "heldout": pose_errors(r.model, dd, val_idx, truth),
                 "alignment": frame_alignment(r.model, dd, train_idx, val_idx, truth),
                 "drift": r.model.pose_drift.summary() if r.model.pose_drift is not None else None}
        results[kind] = {"poses": poses, "psnr": ev["psnr"], "ssim": ev["ssim"], "box_psnr": ev["box_psnr"],
                         "bg_psnr": ev["bg_psnr"],
                         "box_fraction": ev["box_fraction"],
                         "train_psnr_end": r.curve[-1]["train_psnr"] if r.curve else None,
                         "box_iou_mean": ev["box_iou_mean"], "steps": r.step, "train_s": round(r.train_s, 1),
                         "ground_shortfall": r.ground_shortfall, "air_share": r.air_share,
                         "air_prior_steps": r.air_prior_steps,
                         "eval_s": round(time.perf_counter() - t_e, 1), "params": n, "mb": round(n * 4 / 1e6, 2),
                         "planes": r.model.field_config.planes.to_json(), "curve": r.curve,
                         "per_frame_psnr": [round(f["psnr"], 3) for f in ev["frames"]],
                         "heldout_aligned": aligned, "novel": novel}
        print(f"{kind}: held-out PSNR {ev['psnr']:.2f} dB (boxes {ev['box_psnr'] or float('nan'):.2f}, background "
              f"{ev['bg_psnr'] or float('nan'):.2f}, box pixels {100 * (ev['box_fraction'] or 0):.1f} %), "
              f"SSIM {ev['ssim']:.3f}, {r.step} steps in {r.train_s:.0f} s, {n} params; {load_avg()}", flush=True)
        if r.ground_shortfall is not None:
            print(f"  background rays end {r.ground_shortfall:.1%} short of the ground plane (running median), "
                  f"{r.air_share:.1%} of them in the air; air prior in {r.air_prior_steps} of {r.step} steps",
                  flush=True)
        if novel:
            print("  " + summary_line("views from higher up", novel, args.novel_scale), flush=True)
        if aligned:
            print(f"  held-out poses aligned to the field ({aligned['alignment']['steps']} steps, "
                  f"{aligned['seconds']:.0f} s; corrections {aligned['alignment']['trans_rms_m'] * 100:.1f} cm, "
                  f"{aligned['alignment']['rot_rms_deg']:.3f} deg rms): PSNR {aligned['psnr']:.2f} dB (boxes "
                  f"{aligned['box_psnr'] or float('nan'):.2f}, background {aligned['bg_psnr'] or float('nan'):.2f}), "
                  f"SSIM {aligned['ssim']:.3f}", flush=True)
        if poses["heldout"]:
            h = poses["heldout"]
            print("  held-out pose error (median, raw / varying part): " + "; ".join(
                f"{k} {h[k]['centre_raw_m']:.3f} / {h[k]['centre_varying_m']:.3f} m, "
                f"{h[k]['rot_raw_deg']:.3f} / {h[k]['rot_varying_deg']:.3f} deg" for k in ("given", "fitted")),
                flush=True)
        if poses["alignment"]:
            a = poses["alignment"]
            print("  ground misregistration (px, median / mean; train, held-out): " + "; ".join(
                f"{k} {a[k]['train']['median_px']:.2f} / {a[k]['train']['mean_px']:.2f}, "
                f"{a[k]['heldout']['median_px']:.2f} / {a[k]['heldout']['mean_px']:.2f}" for k in ("given", "fitted")),
                flush=True)
    payload = {"flight": str(flight), "frames": dd.n, "train_frames": len(train_idx), "val_frames": len(val_idx),
               "width": dd.data.camera.width, "height": dd.data.camera.height, "budget_s": args.budget_s,
               "jitter_m": args.jitter_m, "jitter_deg": args.jitter_deg, "drift_scale": args.drift_scale,
               "dt_s": args.dt_s, "sfm": args.sfm, "loaded_fits": str(args.load_fits) if args.load_fits else None,
               "load_start": load_start, "load_end": load_avg(), "results": results,
               "threads": torch.get_num_threads(), "overrides": overrides,
               "novel_views": {"scale": args.novel_scale, "every": args.novel_every,
                               "frames": [dd.data.names[i] for i in views.picked]} if views else None}
    if "kplanes" in results:
        payload.update(stock_psnr=results["kplanes"]["psnr"], stock_params=results["kplanes"]["params"],
                       stock_mb=results["kplanes"]["mb"])
    if "kplanes-ext" in results:
        payload.update(extended_psnr=results["kplanes-ext"]["psnr"], extended_params=results["kplanes-ext"]["params"],
                       extended_mb=results["kplanes-ext"]["mb"])
    for kind, key in (("kplanes", "stock"), ("kplanes-ext", "extended")):
        if kind in results and results[kind]["heldout_aligned"]:
            payload[f"{key}_psnr_aligned"] = results[kind]["heldout_aligned"]["psnr"]
        if kind in results and results[kind]["novel"]:  # from higher up, over the ground the training frames saw
            payload[f"{key}_novel_psnr"] = results[kind]["novel"]["novel_psnr_covered"]
    if "stock_psnr" in payload and "extended_psnr" in payload:
        payload["gap_db"] = payload["extended_psnr"] - payload["stock_psnr"]
        print(f"extended - stock = {payload['gap_db']:+.2f} dB at {args.budget_s:.0f} s each", flush=True)
    if "stock_psnr_aligned" in payload and "extended_psnr_aligned" in payload:
        payload["gap_aligned_db"] = payload["extended_psnr_aligned"] - payload["stock_psnr_aligned"]
        print(f"with held-out poses aligned: extended - stock = {payload['gap_aligned_db']:+.2f} dB", flush=True)
    if "stock_novel_psnr" in payload and "extended_novel_psnr" in payload:
        payload["gap_novel_db"] = payload["extended_novel_psnr"] - payload["stock_novel_psnr"]
        print(f"from {args.novel_scale:g}x the distance (covered ground): extended - stock = "
              f"{payload['gap_novel_db']:+.2f} dB", flush=True)
    path = write_json("dynamic", payload, args.json)
    print(f"wrote {path}; total {time.perf_counter() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    main()
