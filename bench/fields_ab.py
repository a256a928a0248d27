"""Short A/B runs of static-field options on the bench scene of bench/fields.py (same flight, same truth).

Each variant trains for a fixed number of iterations (not seconds: A/B results should not depend on
the machine's load) with ``FitConfig`` overrides, then reports held-out 15 m PSNR, simulator-truth
PSNR at 35 m and 50 m (half resolution, as bench/fields.py), mask box IoU on 3 held-out frames
(full resolution, people >= 6 px), seconds per step and the evaluation time.

    python bench/fields_ab.py --iters 400 --variant base: --variant grid:mask_encoding=grid,mask_pos_fraction=0.1
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
from bench.fields import ALTITUDE_VIEWS, half, load_avg, prepare  # noqa: E402


def parse_variant(text: str) -> tuple[str, dict]:
    """``name:key=value,key=value`` -> (name, overrides); values parsed as JSON when they parse."""
    name, _, rest = text.partition(":")
    over = {}
    for item in filter(None, rest.split(",")):
        k, _, v = item.partition("=")
        try:
            over[k] = json.loads(v)
        except json.JSONDecodeError:
            over[k] = v
    return name, over


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iters", type=int, default=400)
    ap.add_argument("--variant", action="append", default=[], help="name:key=value,... (FitConfig fields)")
    ap.add_argument("--masks-of", default="", help="no training: mask box IoU on all held-out frames of the saved "
                                                   "models bench/out/ab_NAME.pt (comma-separated names)")
    ap.add_argument("--flight", type=Path, default=OUT_DIR / "fields_flight")
    ap.add_argument("--json", default=None, help="output path (default bench/out/fields_ab.json)")
    ap.add_argument("--save", action="store_true", help="keep each variant's model as bench/out/ab_NAME.pt")
    args = ap.parse_args()

    import torch

    from fields.data import load_flight
    from fields.evaluation import psnr
    from fields.training import FitConfig, evaluate_frames, fit, load_checkpoint, save_checkpoint

    camera, views = prepare(args.flight)
    data = load_flight(args.flight)
    _, test_idx = data.split(8)
    cam_half = camera.scaled(0.5)
    rows = []
    for name in filter(None, args.masks_of.split(",")):
        model, ck = load_checkpoint(OUT_DIR / f"ab_{name}.pt", "cpu")
        m = evaluate_frames(model, data, test_idx)
        rows.append({"variant": name, "steps": ck["step"], "mask_box_iou_all_heldout": m["box_iou_mean"],
                     "mask_iou_ge_05": m["box_iou_ge_0.5"], "mask_boxes": m["boxes_evaluated"]})
        print(json.dumps(rows[-1]), flush=True)
        write_json("fields_ab", {"rows": rows}, args.json)
    for text in args.variant:
        name, over = parse_variant(text)
        cfg = FitConfig(iters=args.iters, budget_s=None, threads=torch.get_num_threads(), **over)
        load0 = load_avg()
        res = fit(data, cfg)
        if args.save:
            save_checkpoint(OUT_DIR / f"ab_{name}.pt", res.model, None, res.step, res.train_s, cfg, {})
        t0 = time.perf_counter()
        row = {"variant": name, "overrides": over, "steps": res.step, "train_s": round(res.train_s, 1),
               "s_per_step": round(res.train_s / max(res.step, 1), 3), "mb": round(res.model.param_count() * 4e-6, 2)}
        row["heldout15_psnr"] = float(np.mean([
            psnr(res.model.render_image(cam_half, data.cam_from_world[i], with_mask=False)["rgb"],
                 half(data.images[i].numpy())) for i in test_idx]))
        for alt in ALTITUDE_VIEWS:
            row[f"truth{alt}_psnr"] = float(np.mean([
                psnr(res.model.render_image(cam_half, T, with_mask=False)["rgb"], half(rgb))
                for a, _, T, rgb in views if a == alt]))
        m = evaluate_frames(res.model, data, test_idx[:3])  # full resolution, 3 frames (as bench/fields.py)
        row.update(mask_box_iou=m["box_iou_mean"], mask_iou_ge_05=m["box_iou_ge_0.5"], mask_boxes=m["boxes_evaluated"],
                   heldout15_full_psnr=m["psnr"], eval_s=round(time.perf_counter() - t0, 1),
                   load_start=load0, load_end=load_avg())
        rows.append(row)
        print(json.dumps(row), flush=True)
        write_json("fields_ab", {"iters": args.iters, "rows": rows}, args.json)


if __name__ == "__main__":
    main()
