"""The dynamic half of ``uavsim fit``: ``--kind auto`` (choose) and ``--kind kplanes|kplanes-ext`` (fit).

``auto`` looks for labelled people that move (:mod:`fields.scene_kind`), logs the reason and writes
it to ``OUT/kind.json``; a static verdict hands back to the static fit (no time planes), a dynamic
one fits the paper's extended K-Planes. Dynamic fits write ``OUT/dynamic.pt`` (checkpoint,
resumable), ``OUT/fit.json`` (held-out PSNR/SSIM, PSNR inside person boxes, mask box IoU, curve,
parameters, MB, plane sizes, the kind choice) and ``OUT/heldout/`` previews. Default split: every
other frame in time order held out (the paper's); ``--holdout-every k`` changes it.
"""

from __future__ import annotations

import contextlib
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


@contextlib.contextmanager
def denormals_flushed():
    """Flush float denormals to zero inside the block (products of small plane features hit them: ~2x
    slower without), then back to the process default (off): the CPU flag is process-wide state."""
    import torch

    torch.set_flush_denormal(True)
    try:
        yield
    finally:
        torch.set_flush_denormal(False)


def auto_kind(flight: Path, out: Path):
    """The ``--kind auto`` choice (a JSON dict with ``kind`` static|dynamic and ``reason``), written to
    ``out/kind.json`` and logged, and the timed flight (None when frames lack capture times: static)."""
    from fields.data import FlightDataError
    from fields.dynamic_data import load_dynamic_flight

    try:
        dd = load_dynamic_flight(flight)
        choice = decide_kind(flight, dd)
    except FlightDataError as exc:
        if "capture time" not in str(exc):
            raise
        dd, choice = None, {"kind": "static", "reason": f"frames without capture times: {exc}", "evidence": {}}
    out.mkdir(parents=True, exist_ok=True)
    (out / "kind.json").write_text(json.dumps(choice, indent=1, default=float) + "\n")
    log.info("--kind auto: %s (%s)", choice["kind"], choice["reason"])
    return choice, dd


def fit_dynamic_flight(flight: Path, out: Path, kind: str, dd=None, choice: dict | None = None,
                       budget_s: float | None = 300.0, iters: int | None = None, holdout_every: int = 2,
                       threads: int | None = None, seed: int = 0, samples: int | None = None,
                       batch_rays: int | None = None, resume: bool = False,
                       pose_knot_s: float | None = None, air_prior: bool | None = None) -> dict:
    """Fit a ``kplanes`` or ``kplanes-ext`` field → ``out/dynamic.pt`` + ``fit.json`` (+ held-out previews).

    ``pose_knot_s``: spacing of the learned pose-drift knots, s (None: the config default, 1 s on
    telemetry poses and none on SfM-refined ones; 0: none; > 0: that spacing, on SfM poses too).
    ``air_prior``: the empty-air prior on or off (None: on for telemetry poses, off on SfM-refined ones).

    Returns a summary: steps, train_s, params, mb, held-out psnr / ssim / box IoU (None without
    held-out frames). ``dd``: the loaded timed flight (loaded here when None).
    """
    from fields.dynamic_data import load_dynamic_flight
    from fields.dynamic_training import DynamicFitConfig, evaluate_dynamic, fit_dynamic, split, write_dynamic_fit_json

    dd = dd if dd is not None else load_dynamic_flight(flight)
    cfg = DynamicFitConfig(kind=kind, budget_s=budget_s or None, holdout_every=holdout_every, threads=threads,
                           seed=seed, air_prior=air_prior)
    if pose_knot_s is not None:  # 0: take the poses as given; an explicit spacing holds on SfM poses too
        cfg.pose_knot_s = pose_knot_s or None
        cfg.pose_drift_on_sfm = bool(pose_knot_s)
    if iters is not None:
        cfg.iters = iters
    if samples is not None:
        cfg.n_samples = samples
    if batch_rays is not None:
        cfg.batch_rays = batch_rays
    out.mkdir(parents=True, exist_ok=True)
    with denormals_flushed():
        result = fit_dynamic(dd, cfg, out_dir=out, flight=flight, resume=resume)
        _, test = split(dd, cfg.holdout_every)
        heldout = evaluate_dynamic(result.model, dd, test, out_dir=out / "heldout") if test else None
    write_dynamic_fit_json(out / "fit.json", result, heldout, choice)
    n = result.model.param_count()
    return {"kind": kind, "steps": result.step, "train_s": round(result.train_s, 1), "params": n,
            "mb": round(n * 4 / 1e6, 2), "heldout_psnr": heldout["psnr"] if heldout else None,
            "heldout_ssim": heldout["ssim"] if heldout else None,
            "heldout_box_iou": heldout["box_iou_mean"] if heldout else None}


def run(args, out: Path) -> int | None:
    """Handle ``--kind auto|kplanes|kplanes-ext``; returns None when auto chooses the static fit."""
    kind, choice, dd = args.kind, None, None
    if kind == "auto":
        choice, dd = auto_kind(args.flight, out)
        print(f"--kind auto: {choice['kind']} field: {choice['reason']}")
        if choice["kind"] == "static":
            return None
        kind = "kplanes-ext"
    every = 2 if args.holdout_every is None else args.holdout_every
    f = fit_dynamic_flight(args.flight, out, kind, dd, choice, budget_s=args.budget_s, iters=args.iters,
                           holdout_every=every, threads=args.threads, seed=args.seed, samples=args.samples,
                           batch_rays=args.batch_rays, resume=args.resume,
                           pose_knot_s=args.pose_knot_s,
                           air_prior={"auto": None, "on": True, "off": False}[args.air_prior])
    msg = (f"{out}: {kind}, {f['steps']} steps in {f['train_s']:.0f} s, {f['params']} params "
           f"({f['mb']:.1f} MB)")
    if f["heldout_psnr"] is not None:
        msg += f", held-out PSNR {f['heldout_psnr']:.2f} dB SSIM {f['heldout_ssim']:.3f}"
    print(msg)
    return 0
