"""The dynamic field's class mask: boxes from rendered masks at held-out frames, per fit variant.

Table IV needs synthetic labels, and they come from the K-Planes class-mask head. This bench fits
extended (or stock) K-Planes on the Table IV flight of ``bench/dynamic_detect.py`` (Okutama-like
pass, 320x240, 80 frames, even frames train) with ``DynamicFitConfig`` overrides per variant, for a
fixed number of iterations (comparable under any machine load) or a wall-clock budget, then scores
the held-out frames with :func:`fields.dynamic_training.evaluate_dynamic`: PSNR, mask boxes by the
synthesis rules against the frames' labels (IoU, recall / precision at IoU >= 0.5 for people >= 6 px
tall), boxes per frame and the largest foreground probability (a mask that never passes 0.5 gives
no labels at all).

    python bench/dynamic_mask.py --iters 600 --variant base: --variant bg:mask_init_background=0.99 \
        --variant bg_box25:mask_init_background=0.99,box_ray_fraction=0.25
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from bench._common import write_json  # noqa: E402
from bench.dynamic import flight_dir, load_avg, prepare, setup_torch  # noqa: E402
from bench.fields_ab import parse_variant  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=80)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--iters", type=int, default=600, help="training iterations per variant")
    ap.add_argument("--budget-s", type=float, default=None, help="wall-clock budget instead of --iters")
    ap.add_argument("--variant", action="append", default=[],
                    help="name:key=value,... (DynamicFitConfig fields; values JSON, null = None)")
    ap.add_argument("--eval-every", type=int, default=4, help="score every k-th held-out frame")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()

    from fields.dynamic_data import load_dynamic_flight
    from fields.dynamic_training import DynamicFitConfig, evaluate_dynamic, fit_dynamic, split

    setup_torch(args.threads)
    flight = flight_dir(args.width, args.frames)
    prepare(flight, args.frames, args.width)
    dd = load_dynamic_flight(flight)
    _, val_idx = split(dd, 2)
    scored = val_idx[:: args.eval_every]
    results = {}
    for text in args.variant or ["default:"]:
        name, overrides = parse_variant(text)
        cfg = DynamicFitConfig(kind=overrides.pop("kind", "kplanes-ext"), iters=args.iters, budget_s=args.budget_s,
                               seed=0, **overrides)
        load_start = load_avg()
        t = time.perf_counter()
        fit = fit_dynamic(dd, cfg, flight=flight)
        wall = time.perf_counter() - t
        ev = evaluate_dynamic(fit.model, dd, scored)
        row = {"overrides": overrides, "kind": cfg.kind, "steps": fit.step, "train_s": round(fit.train_s, 1),
               "wall_s": round(wall, 1), "load_start": load_start, "load_end": load_avg(),
               **{k: v for k, v in ev.items() if k != "frames"},
               "boxes_per_frame": [r.get("boxes") for r in ev["frames"]],
               "max_foreground": [round(r.get("max_foreground", 0.0), 3) for r in ev["frames"]]}
        results[name] = row
        print(f"{name}: {fit.step} steps {fit.train_s:.0f} s; PSNR {ev['psnr']:.2f}; box IoU {ev['box_iou_mean']}; "
              f"recall {ev['mask_recall']} precision {ev['mask_precision']}; boxes {row['boxes_per_frame']}; "
              f"max fg {row['max_foreground']}", flush=True)
    path = write_json("dynamic_mask", {"flight": str(flight), "scored_frames": len(scored), "variants": results},
                      args.json)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
