"""Static fields: PSNR against wall-clock training time, hash grid vs planes, two samplers.

Scene: the simulator world (seed 0), a 15 m orbit (radius 20 m, pitch -45 deg, 60 frames 320x240,
every 8th held out) written as a recorded flight with true poses (fields.simscene). For each
configuration: fit with a wall-clock budget; at fractions of the budget, PSNR on held-out 15 m
frames and against simulator truth at 35 m (radius 15, pitch -70) and 50 m (radius 10, pitch -80),
4 azimuths each; full-frame PSNR and "covered" PSNR (pixels whose ground point was seen by >= 2
training frames). At the end, mask box IoU on all held-out frames at full resolution (label boxes
>= 6 px on their shorter side; ``evaluate_frames``), the rendered masks are kept in
bench/out/fields_masks_CONFIG.npz and the model is saved as bench/out/fields_CONFIG.pt (input of
bench/synthesis.py). ``--rescore RULES`` scores other ``BoxRules`` on the kept masks without
rendering (the 15 m box IoU, and one-to-one recall / precision for people >= 6 px tall as
bench/synthesis.py scores its views); ``--calibrate`` prints the mask threshold ``uavsim fit`` would
calibrate on them (:mod:`fields.mask_calibration`). Evaluation renders
at half resolution (160x120, truth area-averaged from 320x240) to keep the benchmark affordable
on a busy 2-core machine; evaluation time is not counted as training time.

    python bench/fields.py [--budget-s 300] [--configs hash-occ32,hash-strat,planes-strat,planes-occ]
    python bench/fields.py --configs hash-occ32 --rescore threshold=0.4,relative_threshold=0.5
    python bench/fields.py --configs hash-occ32 --calibrate
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from bench._common import OUT_DIR, write_json  # noqa: E402

CONFIGS = {
    # the `fit` default until session 10; pos25 gives better 15 m mask boxes but worse 35/50 m synthesis precision
    "hash-strat": {"encoding": "hash", "sampler": "stratified", "n_samples": 32, "mask_pos_fraction": 0.0},
    "hash-strat-pos25": {"encoding": "hash", "sampler": "stratified", "n_samples": 32, "mask_pos_fraction": 0.25},
    # the fresh mask head starts as background (0.99) instead of ~75 % foreground everywhere
    "hash-strat-bgstart": {"encoding": "hash", "sampler": "stratified", "n_samples": 32, "mask_pos_fraction": 0.0,
                           "mask_init_background": 0.99},
    "hash-strat-bgstart-pos25": {"encoding": "hash", "sampler": "stratified", "n_samples": 32,
                                 "mask_pos_fraction": 0.25, "mask_init_background": 0.99},
    # bgstart + the mask grid and head at 3x the learning rate (a speckled, unconverged mask at 300 s)
    "hash-strat-bgstart-masklr3": {"encoding": "hash", "sampler": "stratified", "n_samples": 32,
                                   "mask_pos_fraction": 0.0, "mask_init_background": 0.99, "mask_lr_scale": 3.0},
    # the default before session 6: a steeper learning-rate decay (ends at 0.1 lr instead of 0.3 lr)
    "hash-strat-lrf01": {"encoding": "hash", "sampler": "stratified", "n_samples": 32, "mask_pos_fraction": 0.0,
                         "lr_final": 0.1},
    # box pixels with < 10 % of their weight over 10 cm above the ground are taught as background
    "hash-strat-groundcut": {"encoding": "hash", "sampler": "stratified", "n_samples": 32, "mask_pos_fraction": 0.0,
                             "mask_box_min_height_m": 0.1},
    # twice the stratified samples per ray (0.25 m apart along a 45° ray in the 11 m slab instead of 0.49 m)
    "hash-strat-s64": {"encoding": "hash", "sampler": "stratified", "n_samples": 64, "mask_pos_fraction": 0.0},
    "hash-strat-bg384": {"encoding": "hash", "sampler": "stratified", "n_samples": 32, "background_resolution": 384},
    # the default with occupancy cells half as wide (0.25 m): narrower occupied columns around people
    "hash-occ32-fine": {"encoding": "hash", "sampler": "occupancy", "n_samples": 32, "mask_pos_fraction": 0.0,
                        "occupancy_cell_m": (0.25, 0.25, 0.25)},
    "hash-occ": {"encoding": "hash", "sampler": "occupancy", "n_samples": 24},
    # the default with 5x the distortion loss (weights drawn together: people more opaque?); collapsed (session 11)
    "hash-occ32-dist1e2": {"encoding": "hash", "sampler": "occupancy", "n_samples": 32, "mask_pos_fraction": 0.0,
                           "lambda_dist": 1e-2},
    # the default with the occupancy grid's first refresh after 100 steps instead of 200; worse (session 11)
    "hash-occ32-warm100": {"encoding": "hash", "sampler": "occupancy", "n_samples": 32, "mask_pos_fraction": 0.0,
                           "occupancy_warmup": 100},
    # the default + the distortion loss of 256 virtual rays a step looking down from above (within 30 deg of
    # nadir): against density floating over the ground beyond the orbit, which the 35/50 m views expose; it removed
    # most of them but did not raise 50 m PSNR, and cost 1.1 dB held-out (session 13)
    "hash-occ32-topdown": {"encoding": "hash", "sampler": "occupancy", "n_samples": 32, "mask_pos_fraction": 0.0,
                           "lambda_topdown": 5e-3},
    # the box's opaque floor 0.25 m, or by the rule before session 34 (5 % of the box height, >= 0.5 m), below the
    # ground estimate instead of the default 0.1 m: 3 dB less at 50 m with the old rule (session 34)
    "hash-occ32-floor025": {"encoding": "hash", "sampler": "occupancy", "n_samples": 32, "mask_pos_fraction": 0.0,
                            "box_floor_margin_m": 0.25},
    "hash-occ32-floor05": {"encoding": "hash", "sampler": "occupancy", "n_samples": 32, "mask_pos_fraction": 0.0,
                           "box_floor_margin_m": None},
    # a footprint-aware (mip-mapped) background texture, 256² or 512² at its finest: what lies beyond the box at 50 m
    # was seen only at grazing angles from 15 m (session 14)
    "hash-occ32-bgmip256": {"encoding": "hash", "sampler": "occupancy", "n_samples": 32, "mask_pos_fraction": 0.0,
                            "background_resolution": 256, "background_mip": True},
    "hash-occ32-bgmip512": {"encoding": "hash", "sampler": "occupancy", "n_samples": 32, "mask_pos_fraction": 0.0,
                            "background_resolution": 512, "background_mip": True},
    # the 2nd-98th percentile box 8 / 18 m wider on each side (margin 10 / 20 m): the ring the 50 m views see
    # beyond that box, as geometry instead of the flat background texture (sessions 14-15)
    "hash-occ32-margin10": {"encoding": "hash", "sampler": "occupancy", "n_samples": 32, "mask_pos_fraction": 0.0,
                            "box_coverage_pct": 98.0, "box_margin_m": 10.0},
    "hash-occ32-margin20": {"encoding": "hash", "sampler": "occupancy", "n_samples": 32, "mask_pos_fraction": 0.0,
                            "box_coverage_pct": 98.0, "box_margin_m": 20.0},
    # the default box until session 15: the 2nd-98th percentile of the ground hits + 2 m
    "hash-occ32-box98": {"encoding": "hash", "sampler": "occupancy", "n_samples": 32, "mask_pos_fraction": 0.0,
                         "box_coverage_pct": 98.0},
    # the `fit` default (FitConfig) since session 10: 32 samples spread over the occupied cells, not the whole slab;
    # its box spans every ground hit since session 15 (measured as `hash-occ32-allhits` before the default
    # changed; the old box is hash-occ32-box98); its floor 0.1 m below the ground since session 34 (measured as
    # `hash-occ32-floor01` before the default changed; the old floor is hash-occ32-floor05); a quarter of each ray
    # batch drawn from box pixels, both losses importance-weighted, since session 35 (measured as
    # `hash-occ32-pos25-rgbiw` before the default changed; uniform rays are hash-occ32-pos0)
    "hash-occ32": {"encoding": "hash", "sampler": "occupancy", "n_samples": 32, "mask_pos_fraction": 0.25,
                   "rgb_importance_weighted": True},
    "hash-occ32-pos0": {"encoding": "hash", "sampler": "occupancy", "n_samples": 32, "mask_pos_fraction": 0.0},
    # a quarter of each ray batch drawn from box pixels, the RGB loss plain (it leans to the people those rays hit)
    "hash-occ32-pos25": {"encoding": "hash", "sampler": "occupancy", "n_samples": 32, "mask_pos_fraction": 0.25,
                         "rgb_importance_weighted": False},
    # the default's box rays for the first half of the budget only, uniform rays after it
    "hash-occ32-posuntil50": {"encoding": "hash", "sampler": "occupancy", "n_samples": 32, "mask_pos_fraction": 0.25,
                              "rgb_importance_weighted": True, "mask_pos_until": 0.5},
    # a tenth of each ray batch drawn from box pixels, both losses importance-weighted
    "hash-occ32-pos10-rgbiw": {"encoding": "hash", "sampler": "occupancy", "n_samples": 32, "mask_pos_fraction": 0.1,
                               "rgb_importance_weighted": True},
    # the default with each hash level damped where the training frames saw the ground coarser than its cells
    # (fields.footprint; session 16)
    "hash-occ32-lvlfp": {"encoding": "hash", "sampler": "occupancy", "n_samples": 32, "mask_pos_fraction": 0.0,
                         "level_footprint": True},
    "planes-strat": {"encoding": "planes", "sampler": "stratified", "n_samples": 32},
    "planes-occ": {"encoding": "planes", "sampler": "occupancy", "n_samples": 24},
}
ALTITUDE_VIEWS = {35: (15.0, -70.0), 50: (10.0, -80.0)}
AZIMUTHS = (20.0, 110.0, 200.0, 290.0)


def load_avg() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def prepare(flight: Path, seed: int = 0):
    """The flight and the truth views (cached in bench/out)."""
    import cv2

    from fields.simscene import OrbitSpec, write_orbit_flight
    from sim.world import make_world
    from telemetry.camera import Camera, Mount
    from telemetry.frames import orbit_pose

    camera = Camera.from_fov(320, 240, 70.0, Mount(pitch_deg=-45))
    truth_dir = flight / "truth"
    world = None
    if not (flight / "derived" / "poses.json").is_file():
        world = make_world(seed=seed)
        write_orbit_flight(flight, world, camera, OrbitSpec(15.0, 20.0, -45.0, 60), supersample=2)
    views = []
    for alt, (radius, pitch) in ALTITUDE_VIEWS.items():
        for az in AZIMUTHS:
            T = orbit_pose(alt, radius, pitch, az)
            path = truth_dir / f"alt{alt}_az{int(az):03d}.png"
            if not path.is_file():
                world = world or make_world(seed=seed)
                truth_dir.mkdir(parents=True, exist_ok=True)
                res = world.render(camera, T, supersample=2)
                cv2.imwrite(str(path), cv2.cvtColor(res.rgb, cv2.COLOR_RGB2BGR))
            rgb = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
            views.append((alt, az, T, rgb))
    return camera, views


def half(img: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2), interpolation=cv2.INTER_AREA)


def rays_to_ground(camera, T) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every pixel's ray of ``camera`` at ``cam_from_world`` ``T``: origins (N, 3), unit directions (N, 3),
    world ENU, and the distance (N,) m along the ray to the ground plane z = 0 (inf where it does not come down)."""
    uv = camera.pixel_grid().reshape(-1, 2)
    o, d = camera.rays_world(T, uv)
    t = np.where(d[:, 2] < -1e-6, -o[2] / np.minimum(d[:, 2], -1e-6), np.inf)
    return np.broadcast_to(o, d.shape), d, t


def in_frame(camera, uv: np.ndarray, front: np.ndarray) -> np.ndarray:
    """(N,) bool: projected points ``uv`` (N, 2) in front of the camera fall inside its image."""
    return front & (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)


def covered_mask(camera, T, train_Ts) -> np.ndarray:
    """(H, W) bool: the pixel's ground point (z = 0) lies in >= 2 training frames."""
    o, d, t = rays_to_ground(camera, T)
    pts = o + t[:, None] * d
    count = np.zeros(len(t), int)
    for Tt in train_Ts:
        count += in_frame(camera, *camera.project_world(pts, Tt))
    return (count >= 2).reshape(camera.height, camera.width) & np.isfinite(t).reshape(camera.height, camera.width)


def orbit_mask(camera, T, radius_m: float = 20.0) -> np.ndarray:
    """(H, W) bool: the pixel's ground point (z = 0) lies within ``radius_m`` of the scene centre,
    i.e. under the 15 m orbit (radius 20 m) that the training frames were taken from."""
    o, d, t = rays_to_ground(camera, T)
    g = o[:, :2] + np.where(np.isfinite(t), t, 0.0)[:, None] * d[:, :2]
    return ((np.linalg.norm(g, axis=1) <= radius_m) & np.isfinite(t)).reshape(camera.height, camera.width)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--budget-s", type=float, default=300.0)
    ap.add_argument("--configs", default=",".join(CONFIGS))
    ap.add_argument("--eval-fractions", default="0.5,1.0")
    ap.add_argument("--threads", type=int, default=int(os.environ.get("OMP_NUM_THREADS", "2")))
    ap.add_argument("--flight", type=Path, default=OUT_DIR / "fields_flight")
    ap.add_argument("--json", default=None)
    ap.add_argument("--evaluate", action="store_true",
                    help="no training: evaluate the saved bench/out/fields_CONFIG.pt models (mask IoU on all "
                         "held-out frames)")
    ap.add_argument("--rescore", action="append", default=[],
                    help="no rendering: BoxRules overrides key=value,... scored on the masks kept in "
                         "bench/out/fields_masks_CONFIG.npz (repeatable; '' = the defaults)")
    ap.add_argument("--calibrate", action="store_true",
                    help="no rendering: the mask threshold `uavsim fit` would calibrate on the masks kept in "
                         "bench/out/fields_masks_CONFIG.npz (fields.mask_calibration)")
    args = ap.parse_args()
    if args.calibrate:
        for name in args.configs.split(","):
            calibrate_masks(name)
        return
    if args.rescore:
        for name in args.configs.split(","):
            rescore_masks(name, args.rescore)
        return

    import torch

    from fields.data import load_flight
    from fields.evaluation import psnr, ssim
    from fields.training import FitConfig, evaluate_frames, fit, load_checkpoint, save_checkpoint

    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    camera, views = prepare(args.flight)
    print(f"scene ready in {time.perf_counter() - t0:.0f} s; {load_avg()}", flush=True)
    data = load_flight(args.flight)
    train_idx, test_idx = data.split(8)
    cam_half = camera.scaled(0.5)
    train_Ts = [data.cam_from_world[i] for i in train_idx]
    cov = {(alt, az): half(covered_mask(camera, T, train_Ts).astype(np.float32)) > 0.5
           for alt, az, T, _ in views}
    orbit = {(alt, az): half(orbit_mask(camera, T).astype(np.float32)) > 0.5 for alt, az, T, _ in views}
    truth_half = {(alt, az): half(rgb) for alt, az, _, rgb in views}
    held_half = {i: half(data.images[i].numpy()) for i in test_idx}
    fractions = [float(f) for f in args.eval_fractions.split(",")]

    results = []
    for name in args.configs.split(","):
        spec = {} if args.evaluate else CONFIGS[name]  # --evaluate: any bench/out/fields_NAME.pt
        cfg = FitConfig(budget_s=args.budget_s, iters=10**7, threads=args.threads, **spec)
        points = []

        def on_eval(model, step, train_s, points=points, name=name):
            t_e = time.perf_counter()
            row = {"step": step, "train_s": round(train_s, 1)}
            ps, ss = [], []
            for i in test_idx:
                r = model.render_image(cam_half, data.cam_from_world[i], with_mask=False)
                ps.append(psnr(r["rgb"], held_half[i]))
                ss.append(ssim(r["rgb"], held_half[i]))
            row["heldout15_psnr"], row["heldout15_ssim"] = float(np.mean(ps)), float(np.mean(ss))
            for alt in ALTITUDE_VIEWS:
                full, covd, orb, sv = [], [], [], []
                for a, az, T, _ in views:
                    if a != alt:
                        continue
                    r = model.render_image(cam_half, T, with_mask=False)
                    full.append(psnr(r["rgb"], truth_half[(a, az)]))
                    covd.append(psnr(r["rgb"], truth_half[(a, az)], cov[(a, az)]))
                    orb.append(psnr(r["rgb"], truth_half[(a, az)], orbit[(a, az)]))
                    sv.append(ssim(r["rgb"], truth_half[(a, az)]))
                row[f"truth{alt}_psnr"] = float(np.mean(full))
                row[f"truth{alt}_psnr_covered"] = float(np.nanmean(covd))
                row[f"truth{alt}_psnr_orbit"] = float(np.nanmean(orb))
                row[f"truth{alt}_ssim"] = float(np.mean(sv))
            row["eval_s"] = round(time.perf_counter() - t_e, 1)
            row["load"] = load_avg()
            points.append(row)
            print(f"  {name} {json.dumps(row)}", flush=True)

        if args.evaluate:
            model, ck = load_checkpoint(OUT_DIR / f"fields_{name}.pt", "cpu")
            on_eval(model, ck["step"], ck["train_s"])
            masks = evaluate_frames(model, data, test_idx, keep_probs=True)
            save_masks(name, masks.pop("mask_probs"), data)
            results.append({"config": name, "steps": ck["step"], "train_s": ck["train_s"], "points": points,
                            "mask_box_iou_mean": masks["box_iou_mean"], "mask_box_iou_ge_0.5": masks["box_iou_ge_0.5"],
                            "mask_boxes": masks["boxes_evaluated"], "heldout15_full_res_psnr": masks["psnr"]})
            print(f"{name}: mask IoU {masks['box_iou_mean']} ({masks['boxes_evaluated']} boxes)", flush=True)
            write_json("fields_eval", {"results": results}, args.json)
            continue
        print(f"{name}: fitting for {args.budget_s:.0f} s; {load_avg()}", flush=True)
        res = fit(data, cfg, on_eval=on_eval, eval_at_s=[f * args.budget_s for f in fractions[:-1]])
        on_eval(res.model, res.step, res.train_s)
        save_checkpoint(OUT_DIR / f"fields_{name}.pt", res.model, None, res.step, res.train_s, cfg, {})
        masks = evaluate_frames(res.model, data, test_idx, keep_probs=True)  # full resolution, all held out
        save_masks(name, masks.pop("mask_probs"), data)
        n = res.model.param_count()
        results.append({"config": name, **spec, "params": n, "mb": round(n * 4 / 1e6, 2), "steps": res.step,
                        "train_s": round(res.train_s, 1), "s_per_step": round(res.train_s / max(res.step, 1), 3),
                        "points": points, "mask_box_iou_mean": masks["box_iou_mean"],
                        "mask_box_iou_ge_0.5": masks["box_iou_ge_0.5"], "mask_boxes": masks["boxes_evaluated"],
                        "heldout15_full_res_psnr": masks["psnr"], "mask_frames": len(test_idx),
                        "sizing": res.sizing.reasoning if res.sizing else None})
        print(f"{name}: {res.step} steps, {n} params ({n * 4 / 1e6:.1f} MB), mask IoU {masks['box_iou_mean']}",
              flush=True)
        path = write_json("fields", {"budget_s": args.budget_s, "flight": "sim seed 0, 15 m orbit r20 pitch -45, "
                                     "60 frames 320x240, every 8th held out", "eval_resolution": [160, 120],
                                     "results": results}, args.json)
    if args.evaluate:
        return
    plot(results)
    print(f"wrote {path} and {OUT_DIR / 'fields.png'}")


def save_masks(name: str, probs: dict, data) -> Path:
    """Keep the rendered held-out masks and their label boxes (pixel edges) for ``--rescore``."""
    saved = {}
    for i, prob in probs.items():
        saved[f"prob_{i}"] = prob
        saved[f"truth_{i}"] = np.array(data.boxes[i], np.float64).reshape(-1, 5)
    path = OUT_DIR / f"fields_masks_{name}.npz"
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **saved)
    return path


def kept_masks(saved) -> tuple[dict, dict]:
    """The masks ``save_masks`` kept: frame index -> (H, W, K) float32 probabilities, and frame index ->
    label boxes (:class:`fields.mask_boxes.MaskBox`, float pixel edges), in frame order."""
    from fields.evaluation import label_boxes

    ids = sorted(int(k.split("_", 1)[1]) for k in saved.files if k.startswith("prob_"))
    return ({i: saved[f"prob_{i}"].astype(np.float32) for i in ids},
            {i: label_boxes(saved[f"truth_{i}"].tolist()) for i in ids})


def score_masks(saved, rules, min_box_px: float = 6.0) -> dict:
    """Box scores of ``rules`` on kept masks: the ``evaluate_frames`` box IoU (best blob per label box
    >= ``min_box_px`` on its shorter side, any class) and one-to-one recall / precision / mean IoU at
    IoU >= 0.5, same class, people >= ``min_box_px`` tall (the bench/synthesis.py measure)."""
    from fields.evaluation import match_boxes
    from fields.mask_boxes import boxes_from_probabilities
    from fields.synthesis import BoxMatch
    from fields.synthesis import match_boxes as match_one_to_one

    ious, total, pred_n = [], BoxMatch(0, 0, 0, []), 0
    probs, truths = kept_masks(saved)
    for i, prob in probs.items():
        truth = truths[i]
        pred = boxes_from_probabilities(prob, rules)
        pred_n += len(pred)
        ious += match_boxes([t for t in truth if min(t.x1 - t.x0, t.y1 - t.y0) >= min_box_px], pred)
        total = total + match_one_to_one(pred, truth, 0.5, min_box_px)
    return {"box_iou_mean": round(float(np.mean(ious)), 3) if ious else None,
            "box_iou_ge_0.5": round(float(np.mean(np.asarray(ious) >= 0.5)), 3) if ious else None,
            "boxes_evaluated": len(ious), "pred_boxes": pred_n, "recall": round(total.recall, 3),
            "precision": round(total.precision, 3), "mean_iou": round(total.mean_iou, 3)}


def calibrate_masks(name: str) -> None:
    """Print :func:`fields.mask_calibration.calibrate_threshold` on the kept held-out masks of ``name``."""
    from fields.mask_calibration import calibrate_threshold

    probs, truth = kept_masks(np.load(OUT_DIR / f"fields_masks_{name}.npz"))
    print(json.dumps({"config": name, **(calibrate_threshold(probs, truth) or {})}), flush=True)


def rescore_masks(name: str, rule_texts: list[str]) -> None:
    """Print ``score_masks`` for each ``key=value,...`` set of BoxRules overrides."""
    from bench.fields_ab import parse_variant
    from fields.mask_boxes import BoxRules

    saved = np.load(OUT_DIR / f"fields_masks_{name}.npz")
    for text in rule_texts:
        _, over = parse_variant(":" + text)
        print(json.dumps({"config": name, "rules": over, **score_masks(saved, BoxRules(**over))}), flush=True)


def plot(results: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [("heldout15_psnr", "held-out 15 m"), ("truth35_psnr", "truth 35 m"), ("truth50_psnr", "truth 50 m")]
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.6), sharey=False)
    for ax, (k, title) in zip(axes, keys, strict=True):
        for r in results:
            ax.plot([p["train_s"] for p in r["points"]], [p[k] for p in r["points"]], "o-",
                    label=f"{r['config']} ({r['mb']:.0f} MB)")
        ax.set_title(title)
        ax.set_xlabel("training seconds")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("PSNR (dB)")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    fig.savefig(OUT_DIR / "fields.png", dpi=110)


if __name__ == "__main__":
    main()
