"""``uavsim fit`` and ``uavsim render``: fit a static field to a flight, render it at any poses.

``fit FLIGHT --kind static`` reads ``FLIGHT/derived/poses.json`` and writes ``FLIGHT/derived/fields/``:
``static.pt`` (checkpoint, resumable with ``--resume``), ``fit.json`` (held-out PSNR/SSIM and mask
box IoU, training curve, parameter count, MB, sizing reasoning) and ``heldout/`` previews.
``render FLIGHT --poses POSES.json --out DIR [--masks]`` writes ``NAME.png`` per pose (recorded poses, i.e.
any ``source`` but ``"novel"``, get a dynamic field's learned pose-drift correction; NAME = the
pose's ``frame`` stem, else ``pose_NNNNN`` by index) and with ``--masks`` ``NAME_mask.png``
(class id per pixel, 0 = background) and YOLO labels ``labels/NAME.txt`` from the mask blobs.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

log = logging.getLogger(__name__)

KINDS = ("auto", "static", "kplanes", "kplanes-ext")


def register(subparsers) -> None:
    p = subparsers.add_parser("fit", help="fit a radiance field (with mask head) to a recorded flight")
    p.add_argument("flight", type=Path, help="recorded flight folder (needs derived/poses.json)")
    p.add_argument("--kind", choices=KINDS, default="auto",
                   help="field kind; auto = static unless labelled people move (then kplanes-ext)")
    p.add_argument("--budget-s", type=float, default=300.0, help="wall-clock training budget, s (0: none)")
    p.add_argument("--iters", type=int, default=20000, help="maximum iterations")
    p.add_argument("--encoding", choices=("hash", "planes"), default=None, help="spatial encoding")
    p.add_argument("--sampler", choices=("stratified", "occupancy"), default=None, help="ray sampler")
    p.add_argument("--samples", type=int, default=None, help="samples per ray")
    p.add_argument("--batch-rays", type=int, default=None, help="rays per iteration")
    p.add_argument("--budget-mb", type=float, default=None, help="model size budget, MB")
    p.add_argument("--holdout-every", type=int, default=None,
                   help="hold out every k-th frame (0: none; default 8 static, 2 dynamic)")
    p.add_argument("--threads", type=int, default=None, help="CPU threads (default: all)")
    p.add_argument("--pose-knot-s", type=float, default=None,
                   help="dynamic fits: learn a time-smooth pose-drift correction with one knot per this many "
                        "seconds of flight (default: 1 on telemetry poses, none when every pose is SfM-refined; "
                        "0: take the poses as given; a value given here holds on SfM poses too)")
    p.add_argument("--air-prior", choices=("auto", "on", "off"), default="auto",
                   help="dynamic fits: a prior that air is empty unless the images say otherwise, from 10%% of "
                        "training on (auto: on for telemetry poses, off when every pose is SfM-refined)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--resume", action="store_true", help="continue from derived/fields/static.pt")
    p.add_argument("--out", type=Path, default=None, help="output folder (default FLIGHT/derived/fields)")
    p.set_defaults(func=run_fit)

    r = subparsers.add_parser("render", help="render a fitted flight at any poses (images, masks, labels)")
    r.add_argument("flight", type=Path, help="recorded flight folder with derived/fields/static.pt")
    r.add_argument("--poses", type=Path, required=True, help="poses file (DESIGN.md §3 format)")
    r.add_argument("--out", type=Path, required=True, help="output folder")
    r.add_argument("--masks", action="store_true", help="also write mask PNGs and YOLO labels")
    r.add_argument("--min-box-px", type=int, default=4, help="smallest mask blob kept as a label, pixels")
    r.add_argument("--checkpoint", type=Path, default=None,
                   help="default FLIGHT/derived/fields/static.pt, else dynamic.pt (renders at each pose's t_unix_us)")
    r.add_argument("--threads", type=int, default=None)
    r.set_defaults(func=run_render)


def _torch_env(threads: int | None) -> None:
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads
    import torch

    if threads:
        torch.set_num_threads(threads)


def run_fit(args) -> int:
    if args.budget_s < 0 or args.iters <= 0:
        raise ValueError("--budget-s must be >= 0 and --iters > 0")
    _torch_env(args.threads)
    out = args.out or args.flight / "derived" / "fields"
    if args.kind != "static":
        from fields import dynamic_cli

        code = dynamic_cli.run(args, out)  # None: auto chose a static field
        if code is not None:
            return code
    if args.holdout_every is None:
        args.holdout_every = 8
    from fields.data import load_flight
    from fields.training import FitConfig, evaluate_heldout, fit, write_fit_json

    data = load_flight(args.flight)
    cfg = FitConfig(budget_s=args.budget_s or None, iters=args.iters, holdout_every=args.holdout_every,
                    threads=args.threads, seed=args.seed)
    for attr, val in (("encoding", args.encoding), ("sampler", args.sampler), ("n_samples", args.samples),
                      ("batch_rays", args.batch_rays), ("budget_mb", args.budget_mb)):
        if val is not None:
            setattr(cfg, attr, val)
    out.mkdir(parents=True, exist_ok=True)
    result = fit(data, cfg, out_dir=out, flight=args.flight, resume=args.resume)
    _, test = data.split(cfg.holdout_every)
    heldout = evaluate_heldout(result.model, data, test, out_dir=out / "heldout")
    write_fit_json(out / "fit.json", result, cfg, heldout)
    n = result.model.param_count()
    msg = f"{out}: {result.step} steps in {result.train_s:.0f} s, {n} params ({n * 4 / 1e6:.1f} MB)"
    if heldout:
        msg += f", held-out PSNR {heldout['psnr']:.2f} dB SSIM {heldout['ssim']:.3f}"
        if heldout["box_iou_mean"] is not None:
            msg += f", mask box IoU {heldout['box_iou_mean']:.2f}"
    print(msg)
    return 0


def run_render(args) -> int:
    _torch_env(args.threads)
    import cv2
    import numpy as np

    from fields.field_views import load_view_renderer
    from fields.mask_boxes import BoxRules, boxes_from_probabilities
    from telemetry.posesfile import PosesFile

    poses = PosesFile.load(args.poses)
    renderer = load_view_renderer(args.checkpoint, args.flight)
    rules = BoxRules(min_area_px=args.min_box_px)  # the synthesis rules (fields.synthesis)
    camera = poses.camera
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    if args.masks:
        (out / "labels").mkdir(exist_ok=True)
    n_done = n_boxes = 0
    for i, entry in enumerate(poses.frames):
        if entry.cam_from_world is None:
            log.warning("pose %d has no cam_from_world (%s): skipped", i, entry.reason)
            continue
        name = Path(entry.frame).stem if entry.frame else f"pose_{i:05d}"
        T = entry.cam_from_world
        if entry.source != "novel":  # a recorded pose: into the field's world
            T = renderer.field_pose(T, entry.t_unix_us)
        rgb, prob = renderer.render_view(camera, T, entry.t_unix_us, with_mask=args.masks)
        cv2.imwrite(str(out / f"{name}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        if args.masks:
            cv2.imwrite(str(out / f"{name}_mask.png"), np.argmax(prob, axis=-1).astype(np.uint8))
            boxes = boxes_from_probabilities(prob, rules)
            n_boxes += len(boxes)
            (out / "labels" / f"{name}.txt").write_text(
                "".join(b.yolo(camera.width, camera.height) + "\n" for b in boxes))
        n_done += 1
        log.info("rendered %s (%d/%d)", name, i + 1, len(poses.frames))
    if n_done == 0:
        raise ValueError(f"{args.poses}: no posed entries to render")
    print(f"{out}: {n_done} images" + (f", {n_boxes} labelled boxes" if args.masks else ""))
    return 0
