"""Fixtures for the detector tests: tiny exported models and tiny drawn datasets (no sim needed)."""

from pathlib import Path

import cv2
import numpy as np
import pytest


def draw_dataset(root: Path, n: int, size=(96, 64), seed: int = 0, background: int = 0) -> Path:
    """Images with filled rectangles (class = colour) and YOLO labels; ``background`` images have none."""
    rng = np.random.default_rng(seed)
    colours = [(230, 40, 40), (40, 230, 40), (40, 40, 230)]
    for split in ("train", "val"):
        (root / split / "images").mkdir(parents=True, exist_ok=True)
        (root / split / "labels").mkdir(parents=True, exist_ok=True)
        for i in range(n):
            w, h = size
            img = rng.integers(90, 140, (h, w, 3), dtype=np.uint8)
            lines = []
            if i >= background:
                for _ in range(rng.integers(1, 4)):
                    c = int(rng.integers(0, 3))
                    bw, bh = rng.integers(8, 24), rng.integers(8, 24)
                    x0, y0 = rng.integers(0, w - bw), rng.integers(0, h - bh)
                    cv2.rectangle(img, (int(x0), int(y0)), (int(x0 + bw - 1), int(y0 + bh - 1)), colours[c], -1)
                    lines.append(f"{c} {(x0 + bw / 2) / w:.6f} {(y0 + bh / 2) / h:.6f} {bw / w:.6f} {bh / h:.6f}")
            cv2.imwrite(str(root / split / "images" / f"{i:03d}.png"), img[:, :, ::-1])
            if lines:
                (root / split / "labels" / f"{i:03d}.txt").write_text("\n".join(lines) + "\n")
    (root / "data.yaml").write_text(f"path: {root}\ntrain: train/images\nval: val/images\n"
                                    "names:\n  0: red\n  1: green\n  2: blue\n")
    return root / "data.yaml"


@pytest.fixture(scope="session")
def tiny_data(tmp_path_factory) -> Path:
    return draw_dataset(tmp_path_factory.mktemp("data"), 6, background=1)


@pytest.fixture(scope="session")
def onnx_model(tmp_path_factory):
    """(path, torch model) of an untrained 3-class YOLOv8n exported at 64x96 (HxW)."""
    import torch

    from export.onnx_export import export_onnx
    from export.yolo import YOLOv8

    torch.manual_seed(0)
    model = YOLOv8(nc=3, names={0: "standing", 1: "kneeling", 2: "prone"}).eval()
    path = export_onnx(model, tmp_path_factory.mktemp("onnx") / "m.onnx", (64, 96))
    return path, model
