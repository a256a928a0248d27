"""The agent's processing job for one landed flight (run in a child process at low priority).

1. Labels: the flight's ``labels/`` when present; otherwise self-labelling — the current ONNX
   detector runs on every frame and its detections at ``confidence >= self_label_conf`` (0.5)
   become the labels (class names from the model's metadata), so a flight without human labels
   still yields a dataset.
2. Replay: poses → fit → synth → train → eval (:mod:`agent.replay`).
3. Validation: the new R+S detector and the current one are evaluated on the flight's held-out
   real frames; the new model is proposed for swapping only if its mAP50 is not worse. The
   decision goes to ``derived/model_decision.json``; the daemon swaps the file atomically.

``python -m agent.processing FLIGHT --current MODEL.onnx [--quick] [--fit-budget-s S]``
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

log = logging.getLogger(__name__)

SELF_LABEL_CONF = 0.5


def self_label(flight: Path, model: Path, conf: float = SELF_LABEL_CONF) -> int:
    """Write ``labels/`` and ``classes.txt`` from the detector's detections; returns boxes written."""
    from export.infer import Detector, read_image
    from telemetry.flightlog import read_flight

    rec = read_flight(flight)
    det = Detector(model)
    labels = flight / "labels"
    labels.mkdir(exist_ok=True)
    names = [det.names[i] for i in sorted(det.names)]
    (flight / "classes.txt").write_text("".join(n + "\n" for n in names))
    n = 0
    for name, _t in rec.frames:
        img = read_image(flight / "frames" / name)
        h, w = img.shape[:2]
        lines = []
        for d in det.detect(img, conf=conf):
            cx, cy = (d.x0 + d.x1) / 2 / w, (d.y0 + d.y1) / 2 / h
            lines.append(f"{d.class_id} {cx:.6f} {cy:.6f} {(d.x1 - d.x0) / w:.6f} {(d.y1 - d.y0) / h:.6f}\n")
        (labels / (Path(name).stem + ".txt")).write_text("".join(lines))
        n += len(lines)
    log.info("self-labelled %d frames of %s with %s at conf >= %.2f: %d boxes", len(rec.frames), flight.name,
             model, conf, n)
    return n


def decide(flight: Path, current: Path | None, imgsz: int) -> dict:
    from export.evaluate import evaluate_model

    derived = flight / "derived"
    heldout = derived / "datasets" / "real" / "data.yaml"
    new = derived / "detector" / "r+s" / "model.onnx"
    if not new.is_file():
        return {"swap": False, "reason": "no new model was trained"}
    new_map = evaluate_model(new, heldout, imgsz=imgsz).map50
    if current is None or not current.is_file():
        return {"swap": True, "model": str(new), "new_map50": new_map, "current_map50": None,
                "reason": "no current model"}
    cur_map = evaluate_model(current, heldout, imgsz=imgsz).map50
    swap = new_map >= cur_map
    return {"swap": swap, "model": str(new), "new_map50": new_map, "current_map50": cur_map,
            "reason": f"held-out real mAP50 {new_map:.3f} (new) vs {cur_map:.3f} (current)"
                      + ("" if swap else ": keeping the current model")}


def main(argv=None) -> int:
    from agent.cli import configure_logging
    from agent.replay import ReplayOptions, replay, resolve_base

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("flight", type=Path)
    ap.add_argument("--current", default="", help="the detector in use (.onnx)")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--fit-budget-s", type=float, default=300.0)
    ap.add_argument("--base", default="auto", help="detector checkpoint to fine-tune from (auto, none, or .pt)")
    args = ap.parse_args(argv)
    configure_logging(1)
    current = Path(args.current) if args.current else None
    if not (args.flight / "labels").is_dir():
        if current is None or not current.is_file():
            raise SystemExit(f"{args.flight}: no labels and no current detector to self-label with")
        self_label(args.flight, current)
    opts = ReplayOptions(fit_budget_s=args.fit_budget_s, sfm=not args.quick, base_weights=resolve_base(args.base))
    if args.quick:
        opts.epochs, opts.imgsz, opts.fit_budget_s = 5, 320, min(args.fit_budget_s, 60.0)
    replay(args.flight, opts)
    decision = decide(args.flight, current, opts.imgsz)
    out = args.flight / "derived" / "model_decision.json"
    out.write_text(json.dumps(decision, indent=1) + "\n")
    log.info("model decision: %s", decision["reason"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
