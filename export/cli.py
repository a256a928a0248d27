"""``uavsim detect`` (in-flight detector on files, no torch) and ``uavsim detector train|export|eval``."""

from __future__ import annotations

import json
import logging
from pathlib import Path

log = logging.getLogger(__name__)


def register(subparsers) -> None:
    d = subparsers.add_parser("detect", help="run an ONNX detector on image files (the in-flight path)")
    d.add_argument("model", type=Path, help="detector .onnx (uavsim or ultralytics YOLOv8 export)")
    d.add_argument("images", type=Path, nargs="+", help="image files")
    d.add_argument("--conf", type=float, default=0.25, help="score threshold")
    d.add_argument("--iou", type=float, default=0.45, help="NMS IoU threshold (class-aware)")
    d.add_argument("--imgsz", type=int, default=None, help="network input size (default: the model's)")
    d.add_argument("--threads", type=int, default=0, help="onnxruntime intra-op threads (0: default)")
    d.add_argument("--json", action="store_true", help="print JSON instead of text")
    d.set_defaults(func=run_detect)

    p = subparsers.add_parser("detector", help="train, export and evaluate the YOLOv8 detector")
    sub = p.add_subparsers(dest="detector_command", metavar="DETECTOR_COMMAND")
    sub.required = True
    t = sub.add_parser("train", help="train on a YOLO-format dataset (data.yaml)")
    t.add_argument("--data", type=Path, required=True, help="data.yaml (path, train, val, names)")
    t.add_argument("--epochs", type=int, default=20)
    t.add_argument("--batch", type=int, default=16)
    t.add_argument("--imgsz", type=int, default=640)
    t.add_argument("--model", choices=["n", "s"], default="n", help="YOLOv8 scale")
    t.add_argument("--weights", type=Path, default=None, help="start from this checkpoint (.pt)")
    t.add_argument("--out", type=Path, default=Path("runs/detector"), help="folder for last.pt, best.pt, history")
    t.add_argument("--optimizer", choices=["auto", "AdamW", "SGD"], default="auto")
    t.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available)")
    t.add_argument("--budget-s", type=float, default=None, help="stop after the epoch crossing this many seconds")
    t.set_defaults(func=run_train)
    e = sub.add_parser("export", help="checkpoint (.pt) → ONNX (ultralytics layout)")
    e.add_argument("--weights", type=Path, required=True)
    e.add_argument("--out", type=Path, required=True)
    e.add_argument("--imgsz", type=int, default=None, help="input size (default: the training size)")
    e.set_defaults(func=run_export)
    v = sub.add_parser("eval", help="mAP50 and mAP50:95 (COCO, pycocotools) on a dataset split")
    v.add_argument("--model", type=Path, required=True, help=".onnx (flight path) or .pt checkpoint")
    v.add_argument("--data", type=Path, required=True)
    v.add_argument("--imgsz", type=int, default=None)
    v.add_argument("--split", choices=["val", "train"], default="val")
    v.add_argument("--json", type=Path, default=None, help="write the results here")
    v.set_defaults(func=run_eval)
    b = sub.add_parser("pretrain", help="the base detector: YOLOv8n from scratch on simulator renders at 15 m "
                                        "(other worlds), cached; replay and demo fine-tune from it")
    b.add_argument("--out", type=Path, default=None, help="base folder (default: the user cache, "
                                                          "$UAVSIM_CACHE/detector-base)")
    b.add_argument("--train-images", type=int, default=600)
    b.add_argument("--val-images", type=int, default=80)
    b.add_argument("--epochs", type=int, default=60)
    b.add_argument("--budget-s", type=float, default=None, help="stop after the epoch crossing this many seconds")
    b.add_argument("--threads", type=int, default=None)
    b.set_defaults(func=run_pretrain)


def run_detect(args) -> int:
    from export.infer import Detector, read_image

    det = Detector(args.model, threads=args.threads, imgsz=args.imgsz, conf=args.conf, iou=args.iou)
    results = []
    for path in args.images:
        dets = det.detect(read_image(path))
        results.append({"image": str(path), "detections": [d.to_dict() for d in dets]})
        if not args.json:
            print(f"{path}: {len(dets)} detections")
            for d in dets:
                print(f"  {d.name:<12} {d.score:.3f}  {d.x0:7.1f} {d.y0:7.1f} {d.x1:7.1f} {d.y1:7.1f}")
    if args.json:
        print(json.dumps(results, indent=1))
    return 0


def run_train(args) -> int:
    from export.train import TrainConfig, train

    cfg = TrainConfig(data=str(args.data), out=str(args.out), scale=args.model,
                      weights=str(args.weights) if args.weights else None, epochs=args.epochs, batch=args.batch,
                      imgsz=args.imgsz, optimizer=args.optimizer, device=args.device, max_time_s=args.budget_s)
    summary = train(cfg)
    print(f"best {summary['best']} (epoch {summary['best_epoch']}): mAP50 {summary['map50']:.4f} "
          f"mAP50:95 {summary['map50_95']:.4f} in {summary['seconds']:.0f} s")
    return 0


def run_export(args) -> int:
    from export.onnx_export import export_onnx
    from export.train import load_checkpoint

    model, meta = load_checkpoint(args.weights)
    path = export_onnx(model, args.out, args.imgsz or int(meta.get("imgsz", 640)))
    print(f"{path}: {model.nc} classes {list(model.names.values())}")
    return 0


def run_pretrain(args) -> int:
    from export.pretrain import PretrainConfig, pretrain_base

    cfg = PretrainConfig(out=str(args.out or ""), train_images=args.train_images, val_images=args.val_images,
                         epochs=args.epochs, budget_s=args.budget_s, threads=args.threads)
    info = pretrain_base(cfg)
    print(f"base detector {cfg.out_dir() / 'base.pt'}: val mAP50 {info['val_map50']:.3f}, "
          f"mAP50:95 {info['val_map50_95']:.3f} ({info['epochs_run']} epochs, {info['train_s']:.0f} s training)")
    return 0


def run_eval(args) -> int:
    from export.evaluate import evaluate_model

    res = evaluate_model(args.model, args.data, imgsz=args.imgsz, split=args.split, json_out=args.json)
    print(res.table())
    if args.json:
        print(f"wrote {args.json}")
    return 0
