"""Detector acceptance: train YOLOv8n from scratch on simulated 15 m views, then mAP against latency.

Stages (each cached under bench/out/detector/; rerun skips what exists):
  data     render a YOLO dataset: 15 m orbits around several world seeds, 320x240 px
           (train seeds and held-out val seeds are disjoint worlds)
  train    train YOLOv8n from scratch (CPU) — the same code as `uavsim detector pretrain --out bench/out/detector`;
           record the mAP curve, export ONNX, evaluate it through the flight path
  latency  per-frame latency of the in-flight path (letterbox + session.run + decode/NMS) against
           the bare ``session.run`` on the same input, 320 and 640 px, 1 and 2 threads; mAP beside it

    python bench/detector.py [--stage all|data|train|latency] [--epochs N] [--train-images N]
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from bench._common import OUT_DIR, write_json  # noqa: E402

WORK = OUT_DIR / "detector"


def pretrain_config(args):
    from export.pretrain import PretrainConfig

    lo, hi = (int(v) for v in args.train_seeds.split("-"))
    extra = {"weights": args.weights} if args.weights else {}
    return PretrainConfig(out=str(WORK), train_seeds=tuple(range(lo, hi + 1)), train_images=args.train_images,
                          val_images=args.val_images, epochs=args.epochs, batch=args.batch, nbs=args.nbs,
                          budget_s=args.budget_s, extra=extra)


def stage_train(args) -> dict:
    """Train YOLOv8n from scratch at 320 px (= ``uavsim detector pretrain``), then evaluate its ONNX export
    through the flight path."""
    from export.evaluate import evaluate_model
    from export.onnx_export import export_onnx
    from export.pretrain import pretrain_base
    from export.train import load_checkpoint

    info = pretrain_base(pretrain_config(args))
    model, _ = load_checkpoint(WORK / "base.pt")
    onnx_path = export_onnx(model, WORK / "yolov8n_sim15.onnx", 320)
    yaml = WORK / "data" / "data.yaml"
    res = evaluate_model(onnx_path, yaml, imgsz=320)
    print(res.table())
    history = json.loads((WORK / "run" / "history.json").read_text()) if (WORK / "run" / "history.json").is_file() \
        else []
    summary = {**info, "onnx": str(onnx_path), "onnx_eval": res.to_dict(), "history": history}
    (WORK / "train_summary.json").write_text(json.dumps(summary, indent=1, default=str) + "\n")
    return summary


def stage_latency(yaml: Path, repeats: int) -> dict:
    """Flight-path latency against bare session.run, and mAP, per input size and thread count."""
    from export.dataset import load_data_config, load_rgb
    from export.evaluate import evaluate_model
    from export.infer import Detector
    from export.onnx_export import export_onnx
    from export.train import load_checkpoint

    model, _ = load_checkpoint(WORK / "base.pt")
    images = [load_rgb(p) for p in load_data_config(yaml).val[:8]]
    rows = []
    for imgsz in (320, 640):
        path = export_onnx(model, WORK / f"yolov8n_sim15_{imgsz}.onnx", imgsz)
        acc = evaluate_model(path, yaml, imgsz=imgsz)
        for threads in (1, 2):
            det = Detector(path, threads=threads)
            for img in images[:2]:  # warm-up
                det.detect_array(img)
            bare, full, overhead, run_in = [], [], [], []
            for k in range(repeats):
                img = images[k % len(images)]
                blob, _ = det.preprocess(img)
                t0 = time.perf_counter()
                det.run(blob)
                t1 = time.perf_counter()
                parts: dict = {}
                det.detect_array(img, timings=parts)
                t2 = time.perf_counter()
                bare.append(t1 - t0)
                full.append(t2 - t1)
                overhead.append(parts["pre"] + parts["post"])
                run_in.append(parts["run"])
            load = os.getloadavg()[0]
            row = {"imgsz": imgsz, "threads": threads, "run_ms": 1e3 * float(np.median(bare)),
                   "detect_ms": 1e3 * float(np.median(full)), "ratio": float(np.median(full) / np.median(bare)),
                   "pre_post_ms": 1e3 * float(np.median(overhead)),
                   "ratio_same_call": float(1 + np.median(np.array(overhead) / np.array(run_in))),
                   "map50": acc.map50, "map50_95": acc.map50_95, "per_class": acc.per_class,
                   "load1": load, "repeats": repeats}
            rows.append(row)
            print(f"{imgsz} px, {threads} thread(s): session.run {row['run_ms']:.1f} ms, detect "
                  f"{row['detect_ms']:.1f} ms (x{row['ratio']:.3f}; pre+NMS {row['pre_post_ms']:.2f} ms, "
                  f"x{row['ratio_same_call']:.3f} of the same call's run); mAP50 {acc.map50:.3f} "
                  f"mAP50:95 {acc.map50_95:.3f}; load {load:.1f}", flush=True)
    return {"rows": rows}


def plot(history: list[dict], rows: list[dict]) -> None:
    """Left: val mAP against training seconds; right: mAP against flight-path latency."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.8))
    if history:
        t = [r["elapsed_s"] / 60 for r in history]
        a.plot(t, [r["map50"] for r in history], "o-", label="mAP50")
        a.plot(t, [r["map50_95"] for r in history], "s-", label="mAP50:95")
        a.axhline(0.8, color="grey", ls="--", lw=0.8)
        a.set_xlabel("CPU training wall-clock (min)")
        a.set_ylabel("held-out 15 m val mAP (EMA model)")
        a.set_title("YOLOv8n from scratch, 320 px")
        a.legend()
        a.grid(alpha=0.3)
    for r in rows:
        b.plot(r["detect_ms"], r["map50"], "o", color="C0" if r["threads"] == 1 else "C1")
        b.annotate(f"{r['imgsz']}px/{r['threads']}t", (r["detect_ms"], r["map50"]))
    b.set_xlabel("uavsim detect latency per frame (ms)")
    b.set_ylabel("mAP50 (ONNX, flight path)")
    b.set_title("speed against error")
    b.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(OUT_DIR / "detector.png", dpi=120)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stage", default="all", choices=["all", "data", "train", "latency"])
    ap.add_argument("--train-images", type=int, default=600)
    ap.add_argument("--val-images", type=int, default=80)
    ap.add_argument("--train-seeds", default="10-19", help="world seeds of the training split (val: 20-21)")
    ap.add_argument("--epochs", type=int, default=60)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--nbs", type=int, default=8, help="nominal batch (gradient accumulation); = batch: none")
    ap.add_argument("--budget-s", type=float, default=None, help="stop training after this many seconds")
    ap.add_argument("--repeats", type=int, default=40, help="latency samples per configuration")
    ap.add_argument("--weights", default=None, help="continue from this checkpoint instead of scratch")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    yaml = WORK / "data" / "data.yaml"
    if args.stage in ("all", "data"):
        from export.pretrain import render_data

        yaml = render_data(pretrain_config(args))
    if args.stage in ("all", "train"):
        stage_train(args)
    if args.stage in ("all", "latency"):
        lat = stage_latency(yaml, args.repeats)
        summary_path = WORK / "train_summary.json"
        train_summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
        path = write_json("detector", {"train": train_summary, "latency": lat["rows"]}, args.json)
        plot(train_summary.get("history", []), lat["rows"])
        print(f"wrote {path} and {OUT_DIR / 'detector.png'}")


if __name__ == "__main__":
    main()
