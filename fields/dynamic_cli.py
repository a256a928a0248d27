"""The dynamic half of ``uavsim fit``: ``--kind auto`` (choose) and ``--kind kplanes|kplanes-ext`` (fit).

``auto`` looks for labelled people that move (:mod:`fields.scene_kind`), logs the reason and writes
it to ``OUT/kind.json``; a static verdict hands back to the static fit (no time planes), a dynamic
one fits the paper's extended K-Planes. Dynamic fits write ``OUT/dynamic.pt`` (checkpoint,
resumable), ``OUT/fit.json`` (held-out PSNR/SSIM, PSNR inside person boxes, mask box IoU, curve,
parameters, MB, plane sizes, the kind choice) and ``OUT/heldout/`` previews. Default split: every
other frame in time order held out (the paper's); ``--holdout-every k`` changes it.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

log = logging.getLogger(__name__)


def decide_kind(flight: Path, dd) -> dict:
    """The auto choice for a loaded :class:`fields.dynamic_data.DynamicFlightData` as a JSON dict."""
    import numpy as np

    from fields.scene import find_sparse_points
    from fields.scene_kind import choose_kind

    points = find_sparse_points(flight)
    ground_z = float(np.percentile(points[:, 2], 5)) if points is not None and len(points) >= 50 else 0.0
    d = dd.data
    choice = choose_kind(d.camera, d.cam_from_world, dd.times_us, d.boxes, d.has_mask.tolist(), ground_z)
    return {**choice.to_json(), "ground_z": ground_z}


def run(args, out: Path) -> int | None:
    """Handle ``--kind auto|kplanes|kplanes-ext``; returns None when auto chooses the static fit."""
    import torch

    from fields.data import FlightDataError
    from fields.dynamic_data import load_dynamic_flight
    from fields.dynamic_training import (
        DynamicFitConfig,
        evaluate_dynamic,
        fit_dynamic,
        split,
        write_dynamic_fit_json,
    )

    kind, choice = args.kind, None
    try:
        dd = load_dynamic_flight(args.flight)
    except FlightDataError as exc:
        if kind != "auto" or "capture time" not in str(exc):
            raise
        dd, choice = None, {"kind": "static", "reason": f"frames without capture times: {exc}", "evidence": {}}
    if kind == "auto":
        choice = choice or decide_kind(args.flight, dd)
        out.mkdir(parents=True, exist_ok=True)
        (out / "kind.json").write_text(json.dumps(choice, indent=1, default=float) + "\n")
        log.info("--kind auto: %s (%s)", choice["kind"], choice["reason"])
        print(f"--kind auto: {choice['kind']} field: {choice['reason']}")
        if choice["kind"] == "static":
            return None
        kind = "kplanes-ext"
    torch.set_flush_denormal(True)  # products of small plane features hit denormals: ~2x slower without
    every = 2 if args.holdout_every is None else args.holdout_every
    cfg = DynamicFitConfig(kind=kind, budget_s=args.budget_s or None, iters=args.iters, holdout_every=every,
                           threads=args.threads, seed=args.seed)
    if args.samples is not None:
        cfg.n_samples = args.samples
    if args.batch_rays is not None:
        cfg.batch_rays = args.batch_rays
    out.mkdir(parents=True, exist_ok=True)
    result = fit_dynamic(dd, cfg, out_dir=out, flight=args.flight, resume=args.resume)
    _, test = split(dd, cfg.holdout_every)
    heldout = evaluate_dynamic(result.model, dd, test, out_dir=out / "heldout") if test else None
    write_dynamic_fit_json(out / "fit.json", result, cfg, heldout, choice)
    n = result.model.param_count()
    msg = f"{out}: {kind}, {result.step} steps in {result.train_s:.0f} s, {n} params ({n * 4 / 1e6:.1f} MB)"
    if heldout:
        msg += f", held-out PSNR {heldout['psnr']:.2f} dB SSIM {heldout['ssim']:.3f}"
    print(msg)
    return 0
