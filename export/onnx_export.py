"""ONNX export of a :class:`export.yolo.YOLOv8` in ultralytics' layout (DESIGN.md §3).

Single file (no external data), opset 17, input ``images`` [1,3,H,W] float32 RGB 0..1, output
``output0`` [1, 4+nc, N] (cx, cy, w, h input pixels, then sigmoid class scores), no NMS. Metadata
keys as ultralytics writes them (all values strings): ``description, author, date, version,
license, docs, stride, task, batch, imgsz, names, args`` — ``names`` is the text of a dict
``{0: 'standing', ...}``, ``imgsz`` the text of ``[H, W]``.
"""

from __future__ import annotations

import datetime as _dt
import io
import logging
import os
import tempfile
import warnings
from pathlib import Path

import torch

from export.yolo import YOLOv8

log = logging.getLogger(__name__)

OPSET = 17


def metadata(model: YOLOv8, imgsz: tuple[int, int]) -> dict[str, str]:
    return {
        "description": f"uavsim YOLOv8{model.scale} detector (plain torch)",
        "author": "uavsim",
        "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "version": "uavsim-0.1.0",
        "license": "Apache-2.0",
        "docs": "DESIGN.md section 3, Detector ONNX",
        "stride": str(int(model.stride.max().item())),
        "task": "detect",
        "batch": "1",
        "imgsz": str([int(imgsz[0]), int(imgsz[1])]),
        "names": str({int(k): str(v) for k, v in model.names.items()}),
        "args": str({"batch": 1, "half": False, "dynamic": False, "simplify": False, "opset": OPSET, "nms": False}),
    }


def export_onnx(model: YOLOv8, out: str | Path, imgsz: int | tuple[int, int] = 640) -> Path:
    """Write ``model`` (eval mode, CPU, float32) to ``out`` atomically; returns the path."""
    import onnx

    size = (imgsz, imgsz) if isinstance(imgsz, int) else tuple(imgsz)
    stride = int(model.stride.max().item())
    if size[0] % stride or size[1] % stride or min(size) <= 0:
        raise ValueError(f"imgsz must be a positive multiple of {stride}, got {size}")
    model = model.float().cpu().eval()
    dummy = torch.zeros(1, 3, *size)
    buf = io.BytesIO()
    with torch.no_grad(), warnings.catch_warnings():
        # anchors and strides are constants of a fixed-size export: the tracer's warnings about them are expected
        warnings.simplefilter("ignore", torch.jit.TracerWarning)
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(model, (dummy,), buf, opset_version=OPSET, input_names=["images"],
                          output_names=["output0"], do_constant_folding=True, dynamo=False)
    proto = onnx.load_from_string(buf.getvalue())
    for key, value in metadata(model, size).items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.checker.check_model(proto)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=out.parent, suffix=".onnx.tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(proto.SerializeToString())
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    log.info("exported %s (%dx%d, %d classes, %.1f MB)", out, size[1], size[0], model.nc, out.stat().st_size / 1e6)
    return out
