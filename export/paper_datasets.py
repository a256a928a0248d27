"""YOLO-format datasets: Real, Synthetic and Real+Synthetic ("R+S"), as in the paper.

Each dataset is a folder in the layout ultralytics and our trainer read::

    NAME/images/{train,val}/STEM.jpg   (hard links to the originals where the file system allows)
    NAME/labels/{train,val}/STEM.txt   ("class cx cy w h", normalised; empty file = no objects)
    NAME/data.yaml                      path, train, val, names

Real = the flight's frames with their labels, every ``val_every``-th frame held out for
validation. Synthetic = the synthesized views (matched in count to the real training frames by
default, as the paper does), validated on the same held-out real frames. R+S = both training
sets, same validation set. Validation on real frames keeps model selection honest.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp")


@dataclass(frozen=True)
class Sample:
    image: Path
    label: Path | None  # None: no label file (no objects)


def labelled_samples(images_dir: Path, labels_dir: Path) -> list[Sample]:
    """Images in ``images_dir`` (sorted by name) paired with ``labels_dir/STEM.txt`` if present."""
    images = sorted(p for p in Path(images_dir).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    out = []
    for img in images:
        lab = Path(labels_dir) / f"{img.stem}.txt"
        out.append(Sample(img, lab if lab.is_file() else None))
    return out


def _link(src: Path, dst: Path) -> None:
    if dst.exists():
        dst.unlink()
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def _check_label(path: Path, n_classes: int) -> None:
    for k, line in enumerate(path.read_text().splitlines(), start=1):
        parts = line.split()
        if not parts:
            continue
        try:
            c = int(parts[0])
            xywh = [float(v) for v in parts[1:]]
        except ValueError:
            raise ValueError(f"{path}:{k}: not a YOLO label line: {line!r}") from None
        if len(xywh) != 4 or not 0 <= c < n_classes or not all(np.isfinite(xywh)):
            raise ValueError(f"{path}:{k}: expected 'class cx cy w h' with class < {n_classes}, got {line!r}")


def write_dataset(out_dir: str | Path, train: list[Sample], val: list[Sample], names: list[str]) -> Path:
    """Write one dataset folder; returns the path of its ``data.yaml``."""
    out = Path(out_dir)
    if out.exists():
        shutil.rmtree(out)
    for split, samples in (("train", train), ("val", val)):
        (out / "images" / split).mkdir(parents=True)
        (out / "labels" / split).mkdir(parents=True)
        seen = set()
        for s in samples:
            stem = s.image.stem
            if stem in seen:
                raise ValueError(f"two images named {stem!r} in the {split} split of {out}")
            seen.add(stem)
            _link(s.image, out / "images" / split / s.image.name)
            dst = out / "labels" / split / f"{stem}.txt"
            if s.label is not None:
                _check_label(s.label, len(names))
                shutil.copyfile(s.label, dst)
            else:
                dst.write_text("")
    lines = [f"path: {out.resolve()}", "train: images/train", "val: images/val", f"nc: {len(names)}",
             "names:"] + [f"  {i}: {n}" for i, n in enumerate(names)]
    (out / "data.yaml").write_text("\n".join(lines) + "\n")
    return out / "data.yaml"


def split_real(samples: list[Sample], val_every: int = 5) -> tuple[list[Sample], list[Sample]]:
    """Every ``val_every``-th frame (by name order = capture order) goes to validation."""
    if val_every < 2:
        raise ValueError(f"val_every must be >= 2, got {val_every}")
    val = samples[val_every - 1 :: val_every]
    held = {s.image for s in val}
    return [s for s in samples if s.image not in held], val


def build_paper_datasets(real: list[Sample], synthetic: list[Sample], out_root: str | Path,
                         names: list[str], val_every: int = 5, match_count: bool = True,
                         seed: int = 0) -> dict[str, Path]:
    """Write ``real/``, ``synthetic/`` and ``r+s/`` under ``out_root``; returns name → data.yaml."""
    if not real:
        raise ValueError("no real frames: the Real and R+S datasets need the flight's frames")
    real_train, val = split_real(real, val_every)
    syn = list(synthetic)
    if match_count and len(syn) > len(real_train):
        rng = np.random.default_rng(seed)
        keep = np.sort(rng.choice(len(syn), size=len(real_train), replace=False))
        syn = [syn[i] for i in keep]
    root = Path(out_root)
    out = {"real": write_dataset(root / "real", real_train, val, names)}
    if syn:
        out["synthetic"] = write_dataset(root / "synthetic", syn, val, names)
        out["r+s"] = write_dataset(root / "r+s", real_train + syn, val, names)
    return out


def read_class_names(path: str | Path | None, default=("standing", "kneeling", "prone")) -> list[str]:
    """``classes.txt``: one name a line; the default classes when the file is absent."""
    if path is None or not Path(path).is_file():
        return list(default)
    names = [line.strip() for line in Path(path).read_text().splitlines() if line.strip()]
    if not names:
        raise ValueError(f"{path}: no class names")
    return names
