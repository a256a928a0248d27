"""Offline replay of a recorded flight: poses → fit → synth → train → eval → report, resumable.

Every stage writes into the flight's ``derived/`` and leaves a marker (:mod:`agent.stages`), so an
interrupted replay continues where it stopped; ``--force`` runs everything again. Same flight and
seed give the same result. With a simulator truth file (``sim-flight`` writes ``OUT.truth.json``)
the evaluation adds test sets rendered by the simulator at new altitudes — the paper's
experiment (train at 15 m, test at 35-50 m); without it the detectors are compared on the
flight's held-out real frames only.

Outputs: ``derived/poses.json`` (+ SfM exports), ``derived/fields/``, ``derived/synth/``,
``derived/datasets/{real,synthetic,r+s}/``, ``derived/detector/{real,synthetic,r+s}/``
(best.pt, model.onnx), ``derived/eval/``, ``derived/report.md`` with PNG plots.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

from agent.stages import StageRunner

log = logging.getLogger(__name__)

DATASETS = ("real", "synthetic", "r+s")


@dataclass
class ReplayOptions:
    seed: int = 0
    #: field kind: auto (static unless labelled people move; fields.scene_kind), static, kplanes, kplanes-ext
    kind: str = "auto"
    force: bool = False
    sfm: bool = True
    #: field training budget, s
    fit_budget_s: float = 300.0
    #: novel views to synthesise (0: as many as real training frames, the paper's matching)
    synth_count: int = 0
    synth_altitudes_m: tuple[float, ...] = (35.0, 40.0, 45.0, 50.0)
    #: detector training
    epochs: int = 20
    batch: int = 16
    imgsz: int = 640
    train_budget_s: float | None = None
    #: checkpoint (.pt) the detectors are fine-tuned from, as the paper fine-tunes a pretrained YOLOv8n
    #: (see :mod:`export.pretrain`); None: from scratch
    base_weights: str | None = None
    #: simulator truth file: adds altitude test sets rendered by the simulator
    truth: str | None = None
    test_altitudes_m: tuple[float, ...] = (15.0, 35.0, 40.0, 45.0, 50.0)
    test_images_per_altitude: int = 24
    threads: int | None = None


def _derived(flight: Path) -> Path:
    return flight / "derived"


# ---- stages ----------------------------------------------------------------------------------
def stage_poses(flight: Path, opts: ReplayOptions) -> dict:
    """Telemetry poses, refined by SfM unless disabled; per-frame source and reason kept."""
    from telemetry.pose_pipeline import compute_poses

    return compute_poses(flight, sfm=opts.sfm, seed=opts.seed)


def stage_fit(flight: Path, opts: ReplayOptions) -> dict:
    """The scene's field: static (hash grid + mask) or, for moving people, extended K-Planes (``opts.kind``)."""
    from fields.data import load_flight
    from fields.dynamic_cli import auto_kind, fit_dynamic_flight
    from fields.training import FitConfig, evaluate_heldout, fit, write_fit_json

    if opts.kind not in ("auto", "static", "kplanes", "kplanes-ext"):
        raise ValueError(f"field kind must be auto, static, kplanes or kplanes-ext, got {opts.kind!r}")
    out = _derived(flight) / "fields"
    kind, choice, dd = opts.kind, None, None
    if kind == "auto":
        choice, dd = auto_kind(flight, out)
        kind = "static" if choice["kind"] == "static" else "kplanes-ext"
    if kind != "static":
        summary = fit_dynamic_flight(flight, out, kind, dd, choice, budget_s=opts.fit_budget_s, seed=opts.seed,
                                     threads=opts.threads)
        return {**summary, "kind_reason": None if choice is None else choice["reason"],
                "checkpoint": str(out / "dynamic.pt")}
    data = load_flight(flight)
    cfg = FitConfig(budget_s=opts.fit_budget_s, seed=opts.seed, threads=opts.threads)
    out.mkdir(parents=True, exist_ok=True)
    result = fit(data, cfg, out_dir=out, flight=flight)
    _, test = data.split(cfg.holdout_every)
    heldout = evaluate_heldout(result.model, data, test, out_dir=out / "heldout")
    write_fit_json(out / "fit.json", result, cfg, heldout)
    return {"kind": "static", "kind_reason": None if choice is None else choice["reason"],
            "checkpoint": str(out / "static.pt"),
            "steps": result.step, "train_s": round(result.train_s, 1), "params": result.model.param_count(),
            "mb": round(result.model.param_count() * 4 / 1e6, 2),
            "heldout_psnr": None if not heldout else heldout.get("psnr"),
            "heldout_ssim": None if not heldout else heldout.get("ssim"),
            "heldout_box_iou": None if not heldout else heldout.get("box_iou_mean")}


def stage_synth(flight: Path, opts: ReplayOptions, checkpoint: str | None = None) -> dict:
    """Novel views of the field the fit stage made (``checkpoint``; None: static.pt, else dynamic.pt)."""
    from fields.synth_flight import synthesize_flight

    return synthesize_flight(flight, opts.synth_altitudes_m, opts.synth_count, opts.seed, checkpoint=checkpoint)


def stage_train(flight: Path, opts: ReplayOptions, name: str) -> dict:
    from export.onnx_export import export_onnx
    from export.train import fine_tune_config, load_checkpoint, train

    data = _derived(flight) / "datasets" / name / "data.yaml"
    if not data.is_file():
        raise FileNotFoundError(f"{data}: dataset missing (run the synth stage)")
    out = _derived(flight) / "detector" / name
    cfg = fine_tune_config(data=str(data), out=str(out), epochs=opts.epochs, batch=opts.batch, imgsz=opts.imgsz,
                           seed=opts.seed, threads=opts.threads, max_time_s=opts.train_budget_s,
                           weights=opts.base_weights)
    metrics = train(cfg)
    best = out / "best.pt"
    model, meta = load_checkpoint(best)
    export_onnx(model, out / "model.onnx", imgsz=opts.imgsz)
    return {"metrics": metrics, "onnx": str(out / "model.onnx"), "base": opts.base_weights}


def stage_testsets(flight: Path, opts: ReplayOptions) -> dict:
    """Simulator-rendered test sets at each altitude (only with a truth file)."""
    from sim.flight import load_truth
    from sim.testsets import render_altitude_set
    from sim.world import WorldConfig, make_world
    from telemetry.camera import Camera

    truth = load_truth(opts.truth)
    world = make_world(WorldConfig(**truth["world"]))
    camera = Camera.from_json(truth["camera"])
    sets = {}
    for alt in opts.test_altitudes_m:
        out = _derived(flight) / "testsets" / f"alt{int(alt):03d}"
        sets[f"{alt:g} m"] = str(render_altitude_set(world, camera, alt, opts.test_images_per_altitude, out,
                                                     seed=opts.seed + int(alt)))
    return {"sets": sets}


def stage_eval(flight: Path, opts: ReplayOptions, testsets: dict) -> dict:
    from export.evaluate import evaluate_model

    derived = _derived(flight)
    sets = {"held-out real": str(derived / "datasets" / "real" / "data.yaml"), **testsets}
    table = {}
    for model_name in DATASETS:
        onnx = derived / "detector" / model_name / "model.onnx"
        if not onnx.is_file():
            continue
        table[model_name] = {}
        for set_name, yaml in sets.items():
            res = evaluate_model(onnx, yaml, imgsz=opts.imgsz)
            table[model_name][set_name] = res.to_dict()
    (derived / "eval").mkdir(parents=True, exist_ok=True)
    (derived / "eval" / "table.json").write_text(json.dumps(table, indent=1) + "\n")
    return {"table": table}


# ---- the whole chain -------------------------------------------------------------------------
def replay(flight: str | Path, opts: ReplayOptions) -> dict:
    """Run (or resume) every stage; returns the stage summaries and writes ``derived/report.md``."""
    from agent.report import write_report

    flight = Path(flight)
    if not (flight / "frames.csv").is_file():
        raise FileNotFoundError(f"{flight}: not a recorded flight (no frames.csv)")
    if opts.truth is not None and not Path(opts.truth).is_file():
        raise FileNotFoundError(f"{opts.truth}: truth file not found")
    if opts.truth is not None and opts.base_weights:
        from export.pretrain import check_base_for_world
        from sim.flight import load_truth

        check_base_for_world(opts.base_weights, load_truth(opts.truth)["world"].get("seed", 0))
    t0 = time.perf_counter()
    runner = StageRunner(flight, seed=opts.seed, force=opts.force)
    runner.run("poses", lambda: stage_poses(flight, opts))
    fitted = runner.run("fit", lambda: stage_fit(flight, opts))
    runner.run("synth", lambda: stage_synth(flight, opts, fitted.get("checkpoint")))
    for name in DATASETS:
        if (flight / "derived" / "datasets" / name / "data.yaml").is_file():
            runner.run(f"train-{name}", lambda name=name: stage_train(flight, opts, name))
    testsets = {}
    if opts.truth:
        testsets = runner.run("testsets", lambda: stage_testsets(flight, opts))["sets"]
    runner.run("eval", lambda: stage_eval(flight, opts, testsets))
    summaries = dict(runner.summaries)
    report = write_report(flight, summaries, {k: runner.seconds(k) for k in summaries},
                          total_s=time.perf_counter() - t0)
    return {"summaries": summaries, "report": str(report)}


def register(subparsers) -> None:
    p = subparsers.add_parser("replay", help="offline replay: poses → fit → synth → train → eval, resumable")
    p.add_argument("flight", type=Path)
    p.add_argument("--force", action="store_true", help="rerun finished stages")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-sfm", action="store_true", help="telemetry poses only")
    p.add_argument("--kind", default="auto", choices=["auto", "static", "kplanes", "kplanes-ext"],
                   help="field: auto = static unless labelled people move (reason in derived/fields/kind.json)")
    p.add_argument("--fit-budget-s", type=float, default=300.0)
    p.add_argument("--synth-count", type=int, default=0, help="novel views (0: match the real training set)")
    p.add_argument("--altitudes", default="35,40,45,50", help="novel-view altitudes above ground, m")
    p.add_argument("--epochs", type=int, default=20)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--imgsz", type=int, default=640)
    p.add_argument("--train-budget-s", type=float, default=None)
    p.add_argument("--truth", default=None, help="simulator truth file: adds altitude test sets")
    p.add_argument("--base", default="auto", help="detector checkpoint to fine-tune from: auto (the cached base "
                                                  "of `uavsim detector pretrain`, if any), none (from scratch), "
                                                  "or a .pt path")
    p.add_argument("--threads", type=int, default=None)
    p.set_defaults(func=run_cli)


def parse_altitudes(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise ValueError(f"--altitudes must be comma-separated metres, got {text!r}") from None
    if not values or min(values) <= 0:
        raise ValueError(f"--altitudes must be positive metres, got {text!r}")
    return values


def resolve_base(choice: str | None) -> str | None:
    """``auto`` → the cached base detector if there is one; ``none``/empty → None; else the given checkpoint."""
    from export.pretrain import find_base

    if not choice or choice.lower() == "none":
        return None
    base = find_base(None if choice.lower() == "auto" else choice)
    if base is None:
        log.warning("no base detector cached: detectors train from scratch, which needs far more than one "
                    "flight's frames (make one with `uavsim detector pretrain`)")
    return str(base) if base else None


def run_cli(args) -> int:
    opts = ReplayOptions(seed=args.seed, force=args.force, kind=args.kind, sfm=not args.no_sfm,
                         fit_budget_s=args.fit_budget_s,
                         synth_count=args.synth_count, synth_altitudes_m=parse_altitudes(args.altitudes),
                         epochs=args.epochs, batch=args.batch, imgsz=args.imgsz,
                         train_budget_s=args.train_budget_s, truth=args.truth, threads=args.threads,
                         base_weights=resolve_base(args.base))
    out = replay(args.flight, opts)
    print(f"replay finished: {out['report']}")
    return 0
