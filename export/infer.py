"""In-flight detection with onnxruntime: letterbox, run, decode, class-aware NMS. Imports no torch.

Model contract (DESIGN.md §3, the layout of ultralytics' YOLOv8 export): input ``images`` float32
[1,3,H,W] RGB 0..1 letterboxed (grey 114 padding); output [1, 4+nc, N] with rows cx, cy, w, h in
input pixels then per-class scores; class names in the metadata key ``names`` as the text of a
Python dict (``"{0: 'person'}"``), input size in ``imgsz`` (``"[640, 640]"``), ``stride`` ``"32"``.

Boxes returned are in pixels of the *original* image (x0, y0, x1, y1 pixel edges).
"""

from __future__ import annotations

import ast
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

log = logging.getLogger(__name__)


class ModelError(ValueError):
    """The model file is missing, unreadable, or not a detector in the expected layout."""


@dataclass
class Detection:
    """One detection: box in original-image pixels (edges), score in 0..1, class id and name."""

    x0: float
    y0: float
    x1: float
    y1: float
    score: float
    class_id: int
    name: str

    def to_dict(self) -> dict:
        return {"box": [round(self.x0, 2), round(self.y0, 2), round(self.x1, 2), round(self.y1, 2)],
                "score": round(self.score, 4), "class_id": self.class_id, "name": self.name}


@dataclass
class Letterbox:
    """How an image was fitted into the network input: ``input = image * scale + (pad_x, pad_y)``."""

    scale: float
    pad_x: float
    pad_y: float


def letterbox(image: np.ndarray, size: tuple[int, int], color: int = 114) -> tuple[np.ndarray, Letterbox]:
    """Resize keeping aspect ratio and pad to ``size`` = (height, width), centred. Returns HxWx3 uint8."""
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    elif image.ndim == 3 and image.shape[2] == 1:
        image = np.repeat(image, 3, axis=2)
    elif image.ndim == 3 and image.shape[2] == 4:
        image = image[:, :, :3]
    if image.ndim != 3 or image.shape[2] != 3 or image.shape[0] < 1 or image.shape[1] < 1:
        raise ValueError(f"expected an HxW, HxWx1, HxWx3 or HxWx4 image, got shape {image.shape}")
    h, w = image.shape[:2]
    th, tw = size
    r = min(th / h, tw / w)
    nw, nh = max(1, round(w * r)), max(1, round(h * r))
    if (nw, nh) != (w, h):
        image = cv2.resize(image, (nw, nh), interpolation=cv2.INTER_LINEAR)
    px, py = (tw - nw) / 2, (th - nh) / 2
    top, left = round(py - 0.1), round(px - 0.1)
    out = cv2.copyMakeBorder(image, top, th - nh - top, left, tw - nw - left, cv2.BORDER_CONSTANT,
                             value=(color, color, color))
    return out, Letterbox(r, left, top)


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU matrix between x0,y0,x1,y1 boxes a [N,4] and b [M,4]."""
    tl = np.maximum(a[:, None, :2], b[None, :, :2])
    br = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.prod(np.clip(br - tl, 0, None), axis=2)
    area_a = np.prod(a[:, 2:] - a[:, :2], axis=1)
    area_b = np.prod(b[:, 2:] - b[:, :2], axis=1)
    return inter / np.maximum(area_a[:, None] + area_b[None, :] - inter, 1e-12)


def nms(boxes: np.ndarray, scores: np.ndarray, iou_threshold: float, max_keep: int | None = None) -> np.ndarray:
    """Greedy NMS; indices of kept boxes by descending score (at most ``max_keep``)."""
    order = np.argsort(-scores, kind="stable")
    boxes = boxes[order]
    x0, y0, x1, y1 = boxes.T
    area = (x1 - x0) * (y1 - y0)
    keep = []
    alive = np.ones(len(order), dtype=bool)
    for i in range(len(order)):
        if not alive[i]:
            continue
        keep.append(i)
        if max_keep is not None and len(keep) >= max_keep:
            break
        rest = np.nonzero(alive[i + 1:])[0] + i + 1
        if rest.size == 0:
            break
        w = np.clip(np.minimum(x1[i], x1[rest]) - np.maximum(x0[i], x0[rest]), 0, None)
        h = np.clip(np.minimum(y1[i], y1[rest]) - np.maximum(y0[i], y0[rest]), 0, None)
        inter = w * h
        iou = inter / np.maximum(area[i] + area[rest] - inter, 1e-12)
        alive[rest[iou > iou_threshold]] = False
    return order[np.asarray(keep, dtype=np.int64)]


def postprocess(output: np.ndarray, conf: float = 0.25, iou: float = 0.45, multi_label: bool = False,
                max_det: int = 300, max_nms: int = 30000) -> np.ndarray:
    """Raw output [4+nc, N] → [K, 6] rows (x0, y0, x1, y1, score, class) in network-input pixels.

    Class-aware NMS (boxes of different classes never suppress each other). ``multi_label``
    keeps every (box, class) pair above ``conf`` — what mAP evaluation uses — instead of only the
    best class per box.
    """
    pred = output.T  # [N, 4+nc]
    scores = pred[:, 4:]
    if multi_label:
        i, j = np.nonzero(scores > conf)
        score, cls, rows = scores[i, j], j, i
    else:
        cls = scores.argmax(1)
        score = scores[np.arange(len(cls)), cls]
        rows = np.nonzero(score > conf)[0]
        score, cls = score[rows], cls[rows]
    if rows.size == 0:
        return np.zeros((0, 6), dtype=np.float32)
    if rows.size > max_nms:
        top = np.argsort(-score)[:max_nms]
        rows, score, cls = rows[top], score[top], cls[top]
    xywh = pred[rows, :4]
    boxes = np.concatenate((xywh[:, :2] - xywh[:, 2:] / 2, xywh[:, :2] + xywh[:, 2:] / 2), 1)
    # class-aware NMS in one pass: offset each class far apart
    offset = cls[:, None].astype(np.float32) * 7680.0
    keep = nms(boxes + offset, score, iou, max_det)
    return np.concatenate((boxes[keep], score[keep, None], cls[keep, None].astype(np.float32)), 1).astype(np.float32)


def parse_names(meta: dict[str, str], nc: int) -> dict[int, str]:
    """Class names from ONNX metadata (``names`` = text of a dict or list); numbered if absent."""
    text = meta.get("names")
    names: dict[int, str] = {}
    if text:
        try:
            parsed = ast.literal_eval(text)
        except (ValueError, SyntaxError) as exc:
            raise ModelError(f"model metadata 'names' is not a dict or list literal: {text[:80]!r}") from exc
        if isinstance(parsed, (list, tuple)):
            parsed = dict(enumerate(parsed))
        if not isinstance(parsed, dict):
            raise ModelError(f"model metadata 'names' must be a dict or list, got {type(parsed).__name__}")
        names = {int(k): str(v) for k, v in parsed.items()}
    for i in range(nc):
        names.setdefault(i, f"class{i}")
    return names


def available_providers(prefer_gpu: bool = True) -> list[str]:
    """TensorRT / CUDA when this onnxruntime build has them, CPU always last."""
    import onnxruntime as ort

    have = ort.get_available_providers()
    wanted = (["TensorrtExecutionProvider", "CUDAExecutionProvider"] if prefer_gpu else []) + ["CPUExecutionProvider"]
    return [p for p in wanted if p in have]


class Detector:
    """An onnxruntime YOLOv8 detector: ``detect(image RGB uint8) -> list[Detection]``.

    ``imgsz`` (height, width) defaults to the model's fixed input size or its metadata ``imgsz``.
    """

    def __init__(self, model_path: str | Path, *, threads: int = 0, imgsz: int | tuple[int, int] | None = None,
                 conf: float = 0.25, iou: float = 0.45, providers: list[str] | None = None):
        import onnxruntime as ort

        path = Path(model_path)
        if not path.is_file():
            raise ModelError(f"model file not found: {path}")
        opts = ort.SessionOptions()
        if threads:
            opts.intra_op_num_threads = int(threads)
            opts.inter_op_num_threads = 1
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        try:
            self.session = ort.InferenceSession(str(path), sess_options=opts,
                                                providers=providers or available_providers())
        except Exception as exc:  # onnxruntime raises its own Fail/InvalidProtobuf types
            raise ModelError(f"cannot load ONNX model {path}: {str(exc).splitlines()[0][:200]}") from exc
        inputs, outputs = self.session.get_inputs(), self.session.get_outputs()
        if len(inputs) != 1 or len(inputs[0].shape) != 4:
            raise ModelError(f"{path}: expected one [1,3,H,W] input, got {[(i.name, i.shape) for i in inputs]}")
        self.input_name = inputs[0].name
        self.output_name = outputs[0].name
        meta = self.session.get_modelmeta().custom_metadata_map
        self.metadata = dict(meta)
        out_shape = outputs[0].shape
        nc = out_shape[1] - 4 if isinstance(out_shape[1], int) else None
        if nc is None or nc < 1:
            names = parse_names(meta, 0)
            nc = len(names)
        self.names = parse_names(meta, nc)
        self.nc = nc
        self.stride = int(ast.literal_eval(meta.get("stride", "32")))
        self.imgsz = self._input_size(inputs[0].shape, meta, imgsz)
        self.conf, self.iou = conf, iou
        log.info("detector %s: %d classes %s, input %s, providers %s", path.name, nc, list(self.names.values()),
                 self.imgsz, self.session.get_providers())

    def _input_size(self, shape, meta, imgsz) -> tuple[int, int]:
        fixed = (shape[2], shape[3]) if isinstance(shape[2], int) and isinstance(shape[3], int) else None
        if imgsz is not None:
            size = (imgsz, imgsz) if isinstance(imgsz, int) else tuple(imgsz)
            if fixed and tuple(size) != fixed:
                raise ModelError(f"model input is fixed at {fixed[1]}x{fixed[0]}; cannot run at {size[1]}x{size[0]}")
            if size[0] % self.stride or size[1] % self.stride:
                raise ValueError(f"imgsz must be a multiple of the model stride {self.stride}, got {size}")
            return int(size[0]), int(size[1])
        if fixed:
            return int(fixed[0]), int(fixed[1])
        if "imgsz" in meta:
            v = ast.literal_eval(meta["imgsz"])
            return (int(v), int(v)) if isinstance(v, int) else (int(v[0]), int(v[1]))
        return 640, 640

    def preprocess(self, image: np.ndarray) -> tuple[np.ndarray, Letterbox]:
        """RGB (or grey) uint8 image → [1,3,H,W] float32 0..1 and the letterbox transform."""
        if image.dtype != np.uint8:
            raise ValueError(f"expected a uint8 image, got {image.dtype}")
        padded, lb = letterbox(image, self.imgsz)
        blob = np.empty((1, 3, *self.imgsz), dtype=np.float32)
        np.multiply(padded.transpose(2, 0, 1), np.float32(1 / 255), out=blob[0], casting="unsafe")
        return blob, lb

    def run(self, blob: np.ndarray) -> np.ndarray:
        """Bare ``session.run``: [1,3,H,W] → raw [4+nc, N]."""
        return self.session.run([self.output_name], {self.input_name: blob})[0][0]

    def detect_array(self, image: np.ndarray, conf: float | None = None, iou: float | None = None,
                     multi_label: bool = False, max_det: int = 300, timings: dict | None = None) -> np.ndarray:
        """[K,6] rows (x0,y0,x1,y1 original-image pixels, score, class), clipped to the image.

        ``timings``, when given, receives the seconds spent in ``pre``, ``run`` and ``post``.
        """
        t0 = time.perf_counter()
        blob, lb = self.preprocess(image)
        t1 = time.perf_counter()
        raw = self.run(blob)
        t2 = time.perf_counter()
        det = postprocess(raw, self.conf if conf is None else conf, self.iou if iou is None else iou,
                          multi_label=multi_label, max_det=max_det)
        if len(det):
            det[:, [0, 2]] = ((det[:, [0, 2]] - lb.pad_x) / lb.scale).clip(0, image.shape[1])
            det[:, [1, 3]] = ((det[:, [1, 3]] - lb.pad_y) / lb.scale).clip(0, image.shape[0])
        if timings is not None:
            timings.update(pre=t1 - t0, run=t2 - t1, post=time.perf_counter() - t2)
        return det

    def detect(self, image: np.ndarray, conf: float | None = None, iou: float | None = None) -> list[Detection]:
        """Detections in an RGB (or greyscale) uint8 image, best first."""
        return [Detection(float(d[0]), float(d[1]), float(d[2]), float(d[3]), float(d[4]), int(d[5]),
                          self.names.get(int(d[5]), str(int(d[5])))) for d in self.detect_array(image, conf, iou)]


def read_image(path: str | Path) -> np.ndarray:
    """An image file as RGB uint8 (greyscale files stay 2-D)."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise OSError(f"cannot read image {path}")
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[:, :, :3]
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    return img
