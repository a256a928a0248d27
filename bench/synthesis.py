"""Synthesis against simulator truth: views of a fitted field at 35 m and 50 m, boxes from mask blobs.

Scene: the bench/fields.py flight (simulator seed 0, 15 m orbit, 60 frames 320x240, every 8th held
out). The field is the checkpoint bench/fields.py writes (``bench/out/fields_CONFIG.pt``), or a
fresh fit with ``--fit-budget-s`` when there is none. Novel poses: ``fields.novel_poses`` at 35 m
and 50 m (pitch -90..-50 deg, looking at the scene centre, views leaving the observed region
dropped), rendered at 640x480 (same field of view as the flight) through ``fields.synthesis``
(images, labels from mask blobs, as ``uavsim synth`` writes them), timed. The simulator renders the
same poses (supersample 2) as truth. Scores per altitude: recall, precision and mean IoU of
mask-derived boxes against true boxes for people >= 6 px tall (greedy one-to-one, IoU >= 0.5, same
class; smaller people neither missed nor false positives), class-agnostic as well, and PSNR / SSIM
of the image. Box classes are voted by the training frames' labels (``fields.label_transfer``, what
``uavsim synth`` writes); the scores with the mask head's own classes are reported beside them
(``*_mask_class``). Speed: synthetic images per minute (render + boxes + writing) on this process's
threads.

    python bench/synthesis.py [--config hash-occ32] [--count 8] [--size 640x480]
    python bench/synthesis.py --rescore threshold=0.6,min_score=0.6   # box rules on the saved masks

Every run keeps the rendered masks, depths, poses and true boxes in ``bench/out/synthesis_probs.npz`` (``--probs``);
``--rescore RULES`` (``BoxRules`` fields) scores other box rules on them without rendering.
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
from bench.fields import load_avg, prepare  # noqa: E402


class Recorder:
    """Wraps a view renderer; keeps every (rgb, prob, depth) and the time spent rendering."""

    def __init__(self, inner):
        self.inner, self.views, self.seconds = inner, [], 0.0

    def render_view_depth(self, camera, cam_from_world, t_unix_us=None):
        t = time.perf_counter()
        rgb, prob, depth = self.inner.render_view_depth(camera, cam_from_world, t_unix_us)
        self.seconds += time.perf_counter() - t
        self.views.append((rgb, prob, depth))
        return rgb, prob, depth

    def render_view(self, camera, cam_from_world, t_unix_us=None):
        return self.render_view_depth(camera, cam_from_world, t_unix_us)[:2]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="hash-occ32", help="bench/fields.py config whose checkpoint to use")
    ap.add_argument("--checkpoint", type=Path, default=None)
    ap.add_argument("--fit-budget-s", type=float, default=300.0, help="fit this long when there is no checkpoint")
    ap.add_argument("--count", type=int, default=8, help="novel views (half at 35 m, half at 50 m)")
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--min-height-px", type=float, default=6.0)
    ap.add_argument("--pose-seed", type=int, default=0,
                    help="novel-pose seed of the first altitude (+1 for the second); another seed gives "
                         "tuning views apart from the default test views")
    ap.add_argument("--flight", type=Path, default=OUT_DIR / "fields_flight")
    ap.add_argument("--json", default=None)
    ap.add_argument("--probs", type=Path, default=OUT_DIR / "synthesis_probs.npz",
                    help="where this run keeps its masks and true boxes (and what --rescore reads)")
    ap.add_argument("--rescore", action="append", default=[],
                    help="no rendering: BoxRules overrides key=value,... scored on the saved masks (repeatable)")
    args = ap.parse_args()
    if args.rescore:
        rescore(args.rescore, args.min_height_px, args.probs, args.flight)
        return

    import torch

    from fields.data import load_flight
    from fields.evaluation import psnr, ssim
    from fields.field_views import FieldViewRenderer
    from fields.label_transfer import LabelledFrames
    from fields.mask_boxes import boxes_from_probabilities
    from fields.novel_poses import NovelPoseOptions, static_novel_poses
    from fields.synthesis import HIGH_ALTITUDE_RULES, BoxMatch, SynthOptions, match_boxes, synthesize
    from fields.training import FitConfig, fit, load_checkpoint, save_checkpoint
    from sim.world import make_world
    from telemetry.posesfile import Origin

    camera, _ = prepare(args.flight)
    data = load_flight(args.flight)
    train_idx, _ = data.split(8)
    ckpt = args.checkpoint or OUT_DIR / f"fields_{args.config}.pt"
    if ckpt.is_file():
        model, ck = load_checkpoint(ckpt, "cpu")
        fit_info = {"checkpoint": str(ckpt), "steps": ck["step"], "train_s": round(ck["train_s"], 1)}
    else:
        from bench.fields import CONFIGS

        cfg = FitConfig(budget_s=args.fit_budget_s, iters=10**7, threads=torch.get_num_threads(),
                        **CONFIGS[args.config])
        res = fit(data, cfg)
        save_checkpoint(ckpt, res.model, None, res.step, res.train_s, cfg, {})
        model = res.model
        fit_info = {"checkpoint": str(ckpt), "steps": res.step, "train_s": round(res.train_s, 1), "fitted_here": True}
    print(f"field: {fit_info}; {load_avg()}", flush=True)

    w, h = (int(v) for v in args.size.split("x"))
    cam = camera.scaled(w / camera.width)
    if (cam.width, cam.height) != (w, h):
        raise ValueError(f"--size {args.size} does not keep the flight camera's aspect "
                         f"({camera.width}x{camera.height})")
    real = [data.cam_from_world[i] for i in train_idx]
    novel = []
    for k, alt in enumerate((35.0, 50.0)):  # half the views at each altitude
        opts = NovelPoseOptions(altitudes_m=(alt,), count=(args.count + 1 - k) // 2, poses_per_trajectory=1,
                                seed=args.pose_seed + k)
        novel += static_novel_poses(cam, real, opts, ground_z=model.background.ground_z)
    kept = [p for p in novel if p.kept]
    print(f"{len(kept)} novel poses kept, {len(novel) - len(kept)} dropped", flush=True)

    names = list(data.classes)
    rules = HIGH_ALTITUDE_RULES  # what `uavsim synth` uses for static views
    renderer = Recorder(FieldViewRenderer(model, n_classes=len(names)))
    out = OUT_DIR / "synthesis_views"
    load0 = load_avg()
    labels_from = LabelledFrames.from_flight_data(data, train_idx)
    report = synthesize(renderer, cam, Origin(0.0, 0.0, 0.0), [p.entry() for p in kept], out, names,
                        SynthOptions(rules=rules), labels_from=labels_from)
    load1 = load_avg()
    print(f"synthesised {report.images} views in {report.seconds:.1f} s ({report.images_per_minute:.2f}/min); "
          f"{load1}", flush=True)

    world = make_world(seed=0)
    per_alt: dict[float, dict] = {}
    rows, saved = [], {}
    for k, (pose, (rgb, prob, depth)) in enumerate(zip(kept, renderer.views, strict=True)):
        truth = world.render(cam, pose.cam_from_world, supersample=2)
        saved[f"prob_{k}"] = prob.astype(np.float16)
        saved[f"depth_{k}"] = depth.astype(np.float32)
        saved[f"pose_{k}"] = np.asarray(pose.cam_from_world, np.float64)
        saved[f"truth_{k}"] = np.array([[b.class_id, b.x0, b.y0, b.x1, b.y1] for b in truth.boxes], np.float32)
        saved[f"alt_{k}"] = np.float32(pose.altitude_m)
        own = boxes_from_probabilities(prob, rules)
        pred, _ = labels_from.relabel(own, 1.0 - prob[..., 0], depth, cam, pose.cam_from_world,
                                      threshold=rules.threshold)
        m = match_boxes(pred, truth.boxes, 0.5, args.min_height_px)
        m_own = match_boxes(own, truth.boxes, 0.5, args.min_height_px)
        m_any = match_boxes(pred, truth.boxes, 0.5, args.min_height_px, same_class=False)
        row = {"altitude_m": pose.altitude_m, "pitch_deg": round(pose.pitch_deg, 1),
               "psnr": psnr(rgb, truth.rgb), "ssim": ssim(rgb, truth.rgb),
               "true_people": sum((b.y1 - b.y0) >= args.min_height_px for b in truth.boxes), "pred_boxes": len(pred),
               "recall": m.recall, "precision": m.precision, "mean_iou": m.mean_iou,
               "recall_any_class": m_any.recall, "precision_any_class": m_any.precision,
               "recall_mask_class": m_own.recall, "precision_mask_class": m_own.precision}
        rows.append(row)
        print(json.dumps(row), flush=True)
        a = per_alt.setdefault(pose.altitude_m, {"match": BoxMatch(0, 0, 0, []), "any": BoxMatch(0, 0, 0, []),
                                                 "own": BoxMatch(0, 0, 0, []), "psnr": [], "ssim": []})
        a["match"] = a["match"] + m
        a["own"] = a["own"] + m_own
        a["any"] = a["any"] + m_any
        a["psnr"].append(row["psnr"])
        a["ssim"].append(row["ssim"])
    args.probs.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.probs, **saved)
    summary = {}
    for alt, a in sorted(per_alt.items()):
        summary[f"{alt:g}"] = {"views": len(a["psnr"]), "recall": a["match"].recall, "precision": a["match"].precision,
                               "mean_iou": a["match"].mean_iou, "recall_any_class": a["any"].recall,
                               "precision_any_class": a["any"].precision, "mean_iou_any_class": a["any"].mean_iou,
                               "recall_mask_class": a["own"].recall, "precision_mask_class": a["own"].precision,
                               "true_people": a["match"].true_positives + a["match"].false_negatives,
                               "psnr": float(np.mean(a["psnr"])), "ssim": float(np.mean(a["ssim"]))}
        print(f"{alt:g} m: {json.dumps(summary[f'{alt:g}'])}", flush=True)
    path = write_json("synthesis", {"field": fit_info, "size": [w, h], "threads": torch.get_num_threads(),
                                    "images": report.images, "seconds": round(report.seconds, 1),
                                    "render_seconds": round(renderer.seconds, 1),
                                    "images_per_minute": round(report.images_per_minute, 2),
                                    "load_start": load0, "load_end": load1, "per_altitude": summary,
                                    "views": rows, "dropped_poses": len(novel) - len(kept)}, args.json)
    print(f"wrote {path}")


def rescore(rule_texts: list[str], min_height_px: float, probs_path: Path, flight: Path) -> None:
    """Score box rules on the masks and truth boxes the last run saved (no rendering); classes voted by
    the flight's training labels when the run saved depths, else the mask's own."""
    from bench.fields_ab import parse_variant
    from fields.data import load_flight
    from fields.evaluation import label_boxes
    from fields.label_transfer import LabelledFrames
    from fields.mask_boxes import BoxRules, boxes_from_probabilities
    from fields.synthesis import BoxMatch, match_boxes

    saved = np.load(probs_path)
    n = len([k for k in saved.files if k.startswith("prob_")])
    voters = None
    if "depth_0" in saved.files:
        data = load_flight(flight)
        voters = LabelledFrames.from_flight_data(data, data.split(8)[0])
    for text in rule_texts:
        _, over = parse_variant(":" + text)
        rules = BoxRules(**over)
        per_alt: dict[float, BoxMatch] = {}
        for k in range(n):
            truth = label_boxes(saved[f"truth_{k}"].tolist())
            prob = saved[f"prob_{k}"].astype(np.float32)
            pred = boxes_from_probabilities(prob, rules)
            if voters is not None:
                pred, _ = voters.relabel(pred, 1.0 - prob[..., 0], saved[f"depth_{k}"], voters.camera.scaled(
                    prob.shape[1] / voters.camera.width), saved[f"pose_{k}"], threshold=rules.threshold)
            alt = float(saved[f"alt_{k}"])
            per_alt[alt] = per_alt.get(alt, BoxMatch(0, 0, 0, [])) + match_boxes(pred, truth, 0.5, min_height_px)
        print(json.dumps({"rules": over, **{f"{a:g}": {"recall": round(m.recall, 3), "precision": round(m.precision, 3),
                                                      "mean_iou": round(m.mean_iou, 3)}
                                           for a, m in sorted(per_alt.items())}}), flush=True)


if __name__ == "__main__":
    main()
