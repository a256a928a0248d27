"""Detector evaluation: COCO mAP50 and mAP50:95, overall and per class, through pycocotools.

Protocol (how YOLO detectors are usually validated): candidates at conf ≥ 0.001, every class above
it per box (multi-label), class-aware NMS IoU 0.7, up to 300 detections per image, COCO 101-point
interpolated AP over IoU 0.50:0.05:0.95, area 'all'. ONNX models are evaluated through
:class:`export.infer.Detector` — the path the agent flies with; torch models (.pt checkpoints or
in-memory, during training) through the same letterbox and numpy post-processing.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from export.dataset import label_path, load_rgb, read_labels
from export.infer import letterbox, postprocess

log = logging.getLogger(__name__)

#: image RGB uint8 → [K,6] (x0, y0, x1, y1 original pixels, score, class)
Predictor = Callable[[np.ndarray], np.ndarray]

EVAL_CONF = 0.001
EVAL_IOU = 0.7
MAX_DET = 300


@dataclass
class EvalResult:
    """Overall and per-class AP (None for a class without ground truth)."""

    map50: float
    map50_95: float
    per_class: dict[str, dict] = field(default_factory=dict)
    images: int = 0
    instances: int = 0

    def to_dict(self) -> dict:
        return {"map50": self.map50, "map50_95": self.map50_95, "images": self.images,
                "instances": self.instances, "per_class": self.per_class}

    def table(self) -> str:
        lines = [f"{'class':<16}{'instances':>10}{'mAP50':>9}{'mAP50:95':>10}",
                 f"{'all':<16}{self.instances:>10}{self.map50:>9.4f}{self.map50_95:>10.4f}"]
        for name, r in self.per_class.items():
            m50 = "-" if r["map50"] is None else f"{r['map50']:.4f}"
            m = "-" if r["map50_95"] is None else f"{r['map50_95']:.4f}"
            lines.append(f"{name:<16}{r['instances']:>10}{m50:>9}{m:>10}")
        return "\n".join(lines)


def coco_map(gts: list[np.ndarray], preds: list[np.ndarray], sizes: list[tuple[int, int]],
             names: dict[int, str]) -> EvalResult:
    """mAP via pycocotools. ``gts[i]`` [M,5] (class, x0,y0,x1,y1 px); ``preds[i]`` [K,6]; ``sizes`` (h, w)."""
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    images, anns, dets = [], [], []
    for i, ((h, w), gt, pr) in enumerate(zip(sizes, gts, preds, strict=True)):
        images.append({"id": i, "width": int(w), "height": int(h)})
        for c, x0, y0, x1, y1 in gt.tolist():
            anns.append({"id": len(anns) + 1, "image_id": i, "category_id": int(c) + 1, "iscrowd": 0,
                         "bbox": [x0, y0, x1 - x0, y1 - y0], "area": (x1 - x0) * (y1 - y0)})
        for x0, y0, x1, y1, s, c in pr.tolist():
            dets.append({"image_id": i, "category_id": int(c) + 1, "bbox": [x0, y0, x1 - x0, y1 - y0],
                         "score": s})
    instances = {k: 0 for k in names}
    for gt in gts:
        for c in gt[:, 0].astype(int):
            instances[int(c)] = instances.get(int(c), 0) + 1
    per_class = {names[k]: {"instances": instances.get(k, 0), "map50": None, "map50_95": None} for k in names}
    result = EvalResult(0.0, 0.0, per_class, len(images), len(anns))
    if not anns or not dets:
        for k in names:
            if instances.get(k, 0):
                per_class[names[k]].update(map50=0.0, map50_95=0.0)
        return result
    with contextlib.redirect_stdout(io.StringIO()):
        coco_gt = COCO()
        coco_gt.dataset = {"images": images, "annotations": anns,
                           "categories": [{"id": k + 1, "name": n} for k, n in names.items()]}
        coco_gt.createIndex()
        coco_dt = coco_gt.loadRes(dets)
        ev = COCOeval(coco_gt, coco_dt, "bbox")
        ev.params.maxDets = [1, 10, MAX_DET]
        ev.evaluate()
        ev.accumulate()
    prec = ev.eval["precision"][:, :, :, 0, -1]  # [T, R, K] for area 'all', max dets

    def ap(p: np.ndarray) -> float | None:
        v = p[p > -1]
        return float(v.mean()) if v.size else None

    cat_ids = list(ev.params.catIds)
    for k, n in names.items():
        col = cat_ids.index(k + 1)
        if instances.get(k, 0):
            per_class[n].update(map50=ap(prec[0, :, col]), map50_95=ap(prec[:, :, col]))
    with_gt = [r for r in per_class.values() if r["map50"] is not None]
    result.map50 = float(np.mean([r["map50"] for r in with_gt])) if with_gt else 0.0
    result.map50_95 = float(np.mean([r["map50_95"] for r in with_gt])) if with_gt else 0.0
    return result


def evaluate(predict: Predictor, images: list[Path], names: dict[int, str]) -> EvalResult:
    """Run ``predict`` on every image and score it against the YOLO labels."""
    if not images:
        raise ValueError("no images to evaluate")
    gts, preds, sizes = [], [], []
    for p in images:
        img = load_rgb(p)
        h, w = img.shape[:2]
        lab = read_labels(label_path(p), len(names))
        gt = np.zeros((len(lab), 5), np.float32)
        gt[:, 0] = lab[:, 0]
        gt[:, 1], gt[:, 3] = (lab[:, 1] - lab[:, 3] / 2) * w, (lab[:, 1] + lab[:, 3] / 2) * w
        gt[:, 2], gt[:, 4] = (lab[:, 2] - lab[:, 4] / 2) * h, (lab[:, 2] + lab[:, 4] / 2) * h
        gts.append(gt)
        preds.append(np.asarray(predict(img), np.float32).reshape(-1, 6))
        sizes.append((h, w))
    return coco_map(gts, preds, sizes, names)


def torch_predictor(model, imgsz: int) -> Predictor:
    """A torch :class:`export.yolo.YOLOv8` as a predictor with the flight path's letterbox and NMS."""
    import torch

    device = next(model.parameters()).device

    def predict(image: np.ndarray) -> np.ndarray:
        padded, lb = letterbox(image, (imgsz, imgsz))
        x = torch.from_numpy(padded.transpose(2, 0, 1).copy()).to(device).float().div_(255).unsqueeze(0)
        with torch.no_grad():
            out = model(x)[0].float().cpu().numpy()
        det = postprocess(out, EVAL_CONF, EVAL_IOU, multi_label=True, max_det=MAX_DET)
        det[:, [0, 2]] = ((det[:, [0, 2]] - lb.pad_x) / lb.scale).clip(0, image.shape[1])
        det[:, [1, 3]] = ((det[:, [1, 3]] - lb.pad_y) / lb.scale).clip(0, image.shape[0])
        return det

    return predict


def onnx_predictor(path: str | Path, imgsz: int | None = None, threads: int = 0):
    """(predictor, class names) for an ONNX model through the in-flight :class:`Detector`."""
    from export.infer import Detector

    det = Detector(path, threads=threads, imgsz=imgsz)
    return (lambda img: det.detect_array(img, conf=EVAL_CONF, iou=EVAL_IOU, multi_label=True,
                                         max_det=MAX_DET)), det.names


def evaluate_model(model_path: str | Path, data_yaml: str | Path, imgsz: int | None = None,
                   split: str = "val", json_out: str | Path | None = None) -> EvalResult:
    """``uavsim detector eval``: an .onnx or .pt model on a data.yaml split."""
    from export.dataset import load_data_config

    cfg = load_data_config(data_yaml)
    images = getattr(cfg, split)
    model_path = Path(model_path)
    if model_path.suffix == ".onnx":
        predict, names = onnx_predictor(model_path, imgsz)
        if len(names) != cfg.nc:
            raise ValueError(f"model has {len(names)} classes, {data_yaml} has {cfg.nc}")
    elif model_path.suffix == ".pt":
        from export.train import load_checkpoint

        model, meta = load_checkpoint(model_path)
        if model.nc != cfg.nc:
            raise ValueError(f"model has {model.nc} classes, {data_yaml} has {cfg.nc}")
        predict = torch_predictor(model.eval(), imgsz or int(meta.get("imgsz", 640)))
    else:
        raise ValueError(f"model must be .onnx or .pt, got {model_path}")
    result = evaluate(predict, images, cfg.names)
    if json_out:
        Path(json_out).parent.mkdir(parents=True, exist_ok=True)
        Path(json_out).write_text(json.dumps({"model": str(model_path), "data": str(data_yaml),
                                              **result.to_dict()}, indent=2) + "\n")
    return result
