"""Simulator render speed against anti-aliasing error (issue: 640x480 in <= 2 s on 2 cores).

For a set of views (15-50 m, oblique and nadir) renders at supersampling s = 1..4 and compares
each with an s = 6 reference: PSNR of the image and the IoU of the person boxes. Writes
bench/out/render.json and bench/out/render.png.

    python bench/render.py [--width 640 --height 480] [--json OUT]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from bench._common import OUT_DIR, write_json  # noqa: E402
from fields.mask_boxes import box_iou  # noqa: E402
from sim.world import make_world  # noqa: E402
from telemetry.camera import Camera  # noqa: E402
from telemetry.frames import orbit_pose  # noqa: E402

VIEWS = [(15, 20, -50, 0), (15, 20, -90, 60), (35, 25, -55, 120), (50, 30, -60, 200),
         (50, 0, -90, 0), (8, 25, -15, 300)]


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float("inf") if mse == 0 else float(10 * np.log10(255.0**2 / mse))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()

    t0 = time.perf_counter()
    world = make_world(seed=0)
    world_s = time.perf_counter() - t0
    camera = Camera.from_fov(args.width, args.height, 70.0)
    world.render(camera, orbit_pose(*VIEWS[0][:3], VIEWS[0][3]), supersample=1)  # warm-up
    poses = [orbit_pose(alt, radius, pitch, az) for alt, radius, pitch, az in VIEWS]
    refs = [world.render(camera, T, supersample=6) for T in poses]
    rows = []
    for s in (1, 2, 3, 4):
        times, psnrs, ious = [], [], []
        for T, ref in zip(poses, refs, strict=True):
            t0 = time.perf_counter()
            res = world.render(camera, T, supersample=s)
            times.append(time.perf_counter() - t0)
            psnrs.append(psnr(res.rgb, ref.rgb))
            ref_boxes = {b.instance: b for b in ref.boxes}
            ious += [box_iou(b, ref_boxes[b.instance]) for b in res.boxes if b.instance in ref_boxes]
        rows.append({"supersample": s, "mean_s": float(np.mean(times)), "max_s": float(np.max(times)),
                     "psnr_vs_s6_db": float(np.mean(psnrs)), "box_iou_vs_s6": float(np.mean(ious))})
        print(f"s={s}: {rows[-1]['mean_s']:.2f} s/frame (max {rows[-1]['max_s']:.2f}), "
              f"PSNR vs s=6 {rows[-1]['psnr_vs_s6_db']:.1f} dB, box IoU {rows[-1]['box_iou_vs_s6']:.3f}")
    path = write_json("render", {"size": [args.width, args.height], "views": VIEWS,
                                 "world_build_s": world_s, "rows": rows}, args.json)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.plot([r["mean_s"] for r in rows], [r["psnr_vs_s6_db"] for r in rows], "o-")
    for r in rows:
        ax.annotate(f"s={r['supersample']}", (r["mean_s"], r["psnr_vs_s6_db"]))
    ax.set_xlabel(f"seconds per {args.width}x{args.height} frame")
    ax.set_ylabel("PSNR vs s=6 reference (dB)")
    ax.set_title("simulator: render time vs anti-aliasing error")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(OUT_DIR / "render.png", dpi=120)
    print(f"wrote {path} and {OUT_DIR / 'render.png'}")


if __name__ == "__main__":
    main()
