"""Dynamic fields at novel high-altitude views and their geometry, against simulator truth.

Held-out PSNR on a straight pass (bench/dynamic.py, the paper's Table III) asks a field to interpolate
between neighbouring training views; a field that paints the scene on a sheet in the air can pass that
test. Synthesis (issue 8, Table IV) renders the field from *higher* poses, where such a sheet shows.
This bench takes fits kept by ``bench/dynamic.py --save-fits DIR`` and, for every ``--every``-th
held-out frame (time order), measures:

- **geometry**: the field's expected depth at the frame's own pose against the true distance to the
  ground plane (z = 0) along each background pixel's ray (outside the person boxes): the median
  relative error and the share of pixels more than 10 % off (a sheet in the air is far off);
- **novel view**: the frame's true camera moved back along its optical axis until its distance to the
  ground point it looks at is ``--scale`` times larger (2: 15 m -> 30 m altitude), rendered by the
  simulator at the frame's scene time (truth, supersample 2) and by the field at that pose mapped into
  its world by the similarity that lines up its training frames with the true ones
  (:func:`fields.pose_alignment.fit_world_similarity`); PSNR over the frame and over the pixels whose
  ground point >= 2 training frames saw (``covered``), SSIM over the frame. ``--out DIR``: the views
  side by side (truth, then each kind).

``bench/dynamic.py`` scores its own fits the same way (:func:`novel_views`, :func:`score_novel_views`;
its ``--novel-scale``); this bench re-scores kept fits, e.g. at another scale or with the views written out.

    uavsim bench dynamic_novel -- --frames 300 --fits DIR [--scale 2] [--every 5] [--json OUT] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from bench._common import write_json  # noqa: E402
from bench.dynamic import flight_dir, setup_torch  # noqa: E402
from bench.fields import covered_mask, rays_to_ground  # noqa: E402


@dataclass
class NovelViews:
    """Simulator truth for scoring a dynamic flight's fits from farther away (:func:`novel_views`): for each picked
    held-out frame (index into the flight) its raised true pose (OpenCV ``cam_from_world``, true ENU), the truth
    render there (H, W, 3) uint8 sRGB, the raised view's pixels whose ground point >= 2 training frames saw
    (H, W) bool, and at the frame's own true pose each pixel's distance (m) along its ray to the ground z = 0 and
    which pixels are background (outside the label boxes, ray meets the ground), both flat (H * W,); and every
    frame's true pose (``true_cam_from_world``), for lining the fits' worlds up with the true one."""

    picked: list[int]
    pose: dict[int, np.ndarray]
    truth_rgb: dict[int, np.ndarray]
    covered: dict[int, np.ndarray]
    true_depth: dict[int, np.ndarray]
    background: dict[int, np.ndarray]
    true_cam_from_world: dict[int, np.ndarray]


def novel_views(flight: Path, dd, train_idx: list[int], val_idx: list[int], world, scale: float = 2.0,
                every: int = 5) -> NovelViews:
    """Truth views of every ``every``-th held-out frame (time order) of the simulated ``flight`` (its truth
    file beside it; ``world``: the :class:`sim.world.World` it was rendered from), its camera moved back along
    the optical axis to ``scale`` times the distance (1: the frame's own view, as recorded)."""
    from fields.novel_poses import raised_along_axis

    cam = dd.data.camera
    truth_file = flight.with_name(flight.name + ".truth.json")
    truth_rows = {f["frame"]: f for f in json.loads(truth_file.read_text())["frames"]}
    true_pose = {i: np.asarray(truth_rows[dd.data.names[i]]["cam_from_world"]) for i in range(dd.n)}
    picked = list(val_idx[:: max(every, 1)])
    views = NovelViews(picked, {}, {}, {}, {}, {}, true_pose)
    train_true = [true_pose[i] for i in train_idx]
    for i in picked:
        views.pose[i] = raised_along_axis(true_pose[i], scale)
        views.truth_rgb[i] = world.render(cam, views.pose[i], t=float(truth_rows[dd.data.names[i]]["t_scene_s"]),
                                          supersample=2).rgb
        views.covered[i] = covered_mask(cam, views.pose[i], train_true)
        _, _, views.true_depth[i] = rays_to_ground(cam, true_pose[i])  # m along each pixel's ray to z = 0
        views.background[i] = np.isfinite(views.true_depth[i]) & (dd.data.masks[i].numpy().reshape(-1) == 0)
    return views


def score_novel_views(model, dd, train_idx: list[int], views: NovelViews) -> tuple[dict, list[dict], dict]:
    """A fitted dynamic model against ``views``: per frame the depth error at the frame's own pose (median
    relative, share > 10 % off) and PSNR (frame, covered pixels) and SSIM of the raised view, rendered at the
    raised pose mapped into the field's world by the similarity that lines up the training frames with the
    true ones. Returns the means, the per-frame rows and the raised renders (uint8, by frame index)."""
    from fields.evaluation import psnr, ssim
    from fields.pose_alignment import field_pose_from_true, fit_world_similarity

    cam, t01 = dd.data.camera, dd.t01()
    sim = fit_world_similarity(cam, [model.field_pose(dd.data.cam_from_world[i], float(t01[i])) for i in train_idx],
                               [views.true_cam_from_world[i] for i in train_idx])
    sim_scale = float(np.exp(sim[6]))  # field metres -> true metres
    rows, renders = [], {}
    for i in views.picked:
        own = model.render_image(cam, model.field_pose(dd.data.cam_from_world[i], float(t01[i])), float(t01[i]),
                                 with_mask=False)
        valid, true_depth, truth = views.background[i], views.true_depth[i], views.truth_rgb[i]
        rel = np.abs(own["depth"].reshape(-1) * sim_scale - true_depth)[valid] / true_depth[valid]
        r = model.render_image(cam, field_pose_from_true(views.pose[i], sim), float(t01[i]), with_mask=False)
        renders[i] = (np.clip(r["rgb"], 0, 1) * 255).round().astype(np.uint8)
        rows.append({"frame": dd.data.names[i], "depth_rel_median": float(np.median(rel)),
                     "depth_off_10pct": float(np.mean(rel > 0.10)),
                     "novel_psnr": psnr(r["rgb"], truth), "novel_psnr_covered": psnr(r["rgb"], truth, views.covered[i]),
                     "novel_ssim": ssim(r["rgb"], truth)})
    mean = {k: float(np.nanmean([row[k] for row in rows])) for k in rows[0] if k != "frame"} if rows else {}
    return {**mean, "similarity_scale": sim_scale}, rows, renders


def summary_line(kind: str, mean: dict, scale: float) -> str:
    """One log line of :func:`score_novel_views`' means, for views from ``scale`` times the distance."""
    return (f"{kind}: depth off by {100 * mean['depth_rel_median']:.1f} % (median; "
            f"{100 * mean['depth_off_10pct']:.0f} % of pixels > 10 % off); at {scale:g}x the distance "
            f"PSNR {mean['novel_psnr']:.2f} dB (covered {mean['novel_psnr_covered']:.2f}), SSIM "
            f"{mean['novel_ssim']:.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fits", type=Path, required=True, help="DIR of bench/dynamic.py --save-fits DIR (DIR/KIND/)")
    ap.add_argument("--frames", type=int, default=80)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--flight", type=Path, default=None, help="flight folder (default: bench/dynamic.py's)")
    ap.add_argument("--world-seed", type=int, default=0, help="the simulator world of the flight (bench default 0)")
    ap.add_argument("--kinds", default="kplanes,kplanes-ext")
    ap.add_argument("--scale", type=float, default=2.0, help="novel view's distance to the ground / the frame's")
    ap.add_argument("--every", type=int, default=5, help="every k-th held-out frame")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--json", default=None)
    ap.add_argument("--out", type=Path, default=None,
                    help="also write FRAME_novel.png per frame: truth | each kind's render, left to right")
    args = ap.parse_args()

    from fields.dynamic_data import load_dynamic_flight
    from fields.dynamic_training import load_dynamic_checkpoint, split
    from sim.world import make_world

    setup_torch(args.threads)
    flight = args.flight or flight_dir(args.width, args.frames)
    dd = load_dynamic_flight(flight)
    train_idx, val_idx = split(dd, 2)
    t0 = time.perf_counter()
    views = novel_views(flight, dd, train_idx, val_idx, make_world(seed=args.world_seed, dynamic=True), args.scale,
                        args.every)
    print(f"{flight.name}: {len(views.picked)} held-out frames, truth views at {args.scale:g}x the distance rendered "
          f"in {time.perf_counter() - t0:.0f} s", flush=True)
    results = {}
    renders = {i: [views.truth_rgb[i]] for i in views.picked}
    for kind in args.kinds.split(","):
        model, ck = load_dynamic_checkpoint(args.fits / kind / "dynamic.pt")
        mean, rows, kind_renders = score_novel_views(model, dd, train_idx, views)
        for i, img in kind_renders.items():
            renders[i].append(img)
        results[kind] = {**mean, "steps": ck["step"], "train_s": ck["train_s"], "frames": rows}
        print(summary_line(kind, mean, args.scale), flush=True)
    if args.out:
        import cv2

        args.out.mkdir(parents=True, exist_ok=True)
        for i, row in renders.items():
            cv2.imwrite(str(args.out / f"{Path(dd.data.names[i]).stem}_novel.png"),
                        cv2.cvtColor(np.concatenate(row, axis=1), cv2.COLOR_RGB2BGR))
    payload = {"flight": str(flight), "fits": str(args.fits), "scale": args.scale, "every": args.every,
               "frames": [dd.data.names[i] for i in views.picked], "results": results}
    path = write_json(f"dynamic_novel_{args.frames}f", payload, args.json)
    print(f"wrote {path}; total {time.perf_counter() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    main()
