"""The quick demo's field, measured: does a short fit give mask boxes, and how good are they?

Scene: the flight the quick demo records (``agent.demo.QUICK``: simulator seed 0, 15 m orbit,
32 frames 320x240, realistic telemetry noise, poses refined by SfM), cached in
``bench/out/quick_flight``. Each variant fits with ``FitConfig`` overrides for ``--budget-s``
seconds (the demo's 60 s) or ``--iters`` iterations, then reports:

- held-out frames (every 8th): PSNR and mask box IoU against the frames' labels (people >= 6 px);
- novel views as the demo's synth stage samples them (35-50 m, pitch -90..-50 deg, 320x240),
  rendered with masks -> boxes by ``BoxRules``, against the simulator's truth at the same poses:
  boxes per view, recall / precision / mean IoU for people >= 6 px tall (greedy one-to-one at
  IoU >= 0.5, same class). The flight's frame is brought into the simulator's by the rigid
  transform that best fits the SfM camera centres to the true ones (the SfM poses carry a ~1.3 m
  gauge offset; the geodetic origin transform alone would score that offset, not the mask).

    python bench/quick_mask.py --budget-s 60 --variant base: --variant lr:mask_lr_scale=3 [--views 8]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from bench._common import OUT_DIR, write_json  # noqa: E402
from bench.fields import load_avg  # noqa: E402
from bench.fields_ab import parse_variant  # noqa: E402


def prepare_quick_flight(flight: Path, seed: int = 0) -> Path:
    """Record the quick demo's flight and its SfM poses once (as ``uavsim demo --quick`` does)."""
    from agent.demo import QUICK
    from sim.flight import SimFlightConfig, run_sim_flight
    from telemetry.pose_pipeline import compute_poses

    if not (flight / "frames.csv").is_file():
        flight.parent.mkdir(parents=True, exist_ok=True)
        run_sim_flight(flight, SimFlightConfig(frames=QUICK.frames, width=QUICK.width, height=QUICK.height,
                                               seed=seed, noise="realistic"))
    if not (flight / "derived" / "poses.json").is_file():
        compute_poses(flight, sfm=QUICK.sfm, seed=seed)
    return flight


def novel_views(flight: Path, model, count: int, seed: int = 0):
    """The synth stage's novel poses (flight frame) and the same poses in the simulator's frame."""
    from fields.novel_poses import NovelPoseOptions, static_novel_poses
    from sim.flight import load_truth, truth_path
    from telemetry.frames import camera_center
    from telemetry.posesfile import PosesFile
    from telemetry.sfm import umeyama

    poses = PosesFile.load(flight / "derived" / "poses.json")
    novel = static_novel_poses(poses.camera, [e.cam_from_world for e in poses.posed()],
                               NovelPoseOptions(altitudes_m=(35.0, 40.0, 45.0, 50.0), count=count, seed=seed),
                               ground_z=model.background.ground_z)
    truth = load_truth(truth_path(flight))
    true_c = {f["frame"]: camera_center(f["cam_from_world"]) for f in truth["frames"]}
    pairs = [(camera_center(e.cam_from_world), true_c[e.frame]) for e in poses.posed() if e.frame in true_c]
    _, R, t = umeyama(np.array([a for a, _ in pairs]), np.array([b for _, b in pairs]), with_scale=False)
    sim_from_flight = np.eye(4)
    sim_from_flight[:3, :3], sim_from_flight[:3, 3] = R, t
    kept = [p for p in novel if p.kept]
    return poses.camera, truth, [(p, p.cam_from_world @ np.linalg.inv(sim_from_flight)) for p in kept]


def score_views(model, flight: Path, count: int, rules, min_height_px: float = 6.0) -> dict:
    """Novel views of the field vs the simulator: boxes per view, recall / precision / IoU."""
    from fields.field_views import FieldViewRenderer
    from fields.mask_boxes import boxes_from_probabilities
    from fields.synthesis import BoxMatch, match_boxes
    from sim.world import WorldConfig, make_world
    from telemetry.camera import Camera

    camera, truth, views = novel_views(flight, model, count)
    world = make_world(WorldConfig(**truth["world"]))
    cam = Camera.from_json(truth["camera"])
    renderer = FieldViewRenderer(model, n_classes=model.field_config.n_classes)
    total, boxes_per_view, true_people = BoxMatch(0, 0, 0, []), [], 0
    for pose, T_sim in views:
        _, prob = renderer.render_view(camera, pose.cam_from_world)
        pred = boxes_from_probabilities(prob, rules)
        gt = world.render(cam, T_sim, supersample=2).boxes
        m = match_boxes(pred, gt, 0.5, min_height_px)
        total = total + m
        boxes_per_view.append(len(pred))
        true_people += sum((b.y1 - b.y0) >= min_height_px for b in gt)
    return {"views": len(views), "boxes_per_view": boxes_per_view, "true_people_ge_min": true_people,
            "recall": total.recall, "precision": total.precision, "mean_iou": total.mean_iou}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--budget-s", type=float, default=60.0)
    ap.add_argument("--iters", type=int, default=None, help="fixed iterations instead of the budget")
    ap.add_argument("--variant", action="append", default=[], help="name:key=value,... (FitConfig fields)")
    ap.add_argument("--views", type=int, default=8, help="novel views to score (the demo synthesises 16)")
    ap.add_argument("--rescore", default="", help="no training: score the saved bench/out/quick_NAME.pt models "
                                                  "(comma-separated names)")
    ap.add_argument("--flight", type=Path, default=OUT_DIR / "quick_flight")
    ap.add_argument("--json", default=None, help="output path (default bench/out/quick_mask.json)")
    args = ap.parse_args()

    import torch

    from fields.data import load_flight
    from fields.mask_boxes import BoxRules
    from fields.training import FitConfig, evaluate_frames, fit, load_checkpoint, save_checkpoint

    t0 = time.perf_counter()
    flight = prepare_quick_flight(args.flight)
    print(f"flight ready in {time.perf_counter() - t0:.0f} s; {load_avg()}", flush=True)
    data = load_flight(flight)
    _, test_idx = data.split(8)
    rows = []
    budget = None if args.iters else args.budget_s
    jobs = [(name, None) for name in filter(None, args.rescore.split(","))] + \
        [parse_variant(text) for text in args.variant]
    for name, over in jobs:
        load0 = load_avg()
        if over is None:
            model, ck = load_checkpoint(OUT_DIR / f"quick_{name}.pt", "cpu")
            over = {k: v for k, v in ck["fit_config"].items() if v != getattr(FitConfig(), k)}
            steps, mask_steps, train_s = ck["step"], ck.get("mask_steps"), ck["train_s"]
        else:
            cfg = FitConfig(iters=args.iters or 10**7, budget_s=budget, threads=torch.get_num_threads(), **over)
            res = fit(data, cfg, flight=flight)
            model, steps, mask_steps, train_s = res.model, res.step, res.mask_steps, res.train_s
            save_checkpoint(OUT_DIR / f"quick_{name}.pt", model, None, steps, train_s, cfg,
                            {"mask_steps": mask_steps})
        t1 = time.perf_counter()
        held = evaluate_frames(model, data, test_idx)
        row = {"variant": name, "overrides": over, "steps": steps, "mask_steps": mask_steps,
               "train_s": round(train_s, 1), "heldout_psnr": held["psnr"], "heldout_box_iou": held["box_iou_mean"],
               "heldout_iou_ge_05": held["box_iou_ge_0.5"], "heldout_people": held["boxes_evaluated"]}
        row["novel"] = score_views(model, flight, args.views, BoxRules())
        row.update(eval_s=round(time.perf_counter() - t1, 1), load_start=load0, load_end=load_avg())
        rows.append(row)
        print(json.dumps(row), flush=True)
        write_json("quick_mask", {"budget_s": budget, "iters": args.iters, "rows": rows}, args.json)


if __name__ == "__main__":
    main()
