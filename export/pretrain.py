"""A base detector, trained from scratch on simulator renders: the stand-in for pretrained weights.

The paper fine-tunes a COCO-pretrained YOLOv8n on each dataset (Real, Synthetic, R+S). Nothing may be
downloaded here, and a few dozen frames of one flight are far too few to train YOLOv8n from scratch
(the quick demo's detectors score 0 mAP that way). So uavsim trains its own base once: YOLOv8n on
:mod:`sim.trainsets` renders at 15 m over worlds 10-19, validated on worlds 20-21, and the replay
fine-tunes from it. The base has seen the training altitude only, like COCO has few high-altitude
views, so what a detector gains at 35-50 m still comes from the synthetic data.

Layout of ``out`` (default: the user cache, :func:`default_base_dir`)::

    data/{train,val}/{images,labels}, data/data.yaml   rendered set (resumable)
    run/                                                 training run (best.pt, last.pt, history)
    base.pt                                              the chosen checkpoint (copied from run/best.pt)
    base.json                                            provenance: seeds, sizes, mAP, seconds, command

A flight whose world seed is one of the base's training or validation seeds would leak test data into
the base; :func:`check_base_for_world` says so.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

log = logging.getLogger(__name__)

BASE_KIND = "uavsim-detector-base"


def default_base_dir() -> Path:
    """``$UAVSIM_CACHE/detector-base`` or ``~/.cache/uavsim/detector-base`` (XDG_CACHE_HOME honoured)."""
    cache = os.environ.get("UAVSIM_CACHE")
    if not cache:
        cache = str(Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "uavsim")
    return Path(cache) / "detector-base"


@dataclass
class PretrainConfig:
    """What the base sees and how long it trains. Defaults: the run recorded in bench/RESULTS.md."""

    out: str = ""                                   #: folder; empty: :func:`default_base_dir`
    train_seeds: tuple[int, ...] = tuple(range(10, 20))
    val_seeds: tuple[int, ...] = (20, 21)
    train_images: int = 600
    val_images: int = 80
    altitude_m: float = 15.0
    width: int = 320                                #: rendered image size, px
    height: int = 240
    imgsz: int = 320
    epochs: int = 60
    batch: int = 8
    nbs: int = 8                                    #: no gradient accumulation: more updates on a small set
    budget_s: float | None = None                   #: stop after the epoch crossing this many seconds
    threads: int | None = None
    seed: int = 0
    extra: dict = field(default_factory=dict)       #: more TrainConfig fields (e.g. weights to continue from)
    world_overrides: dict = field(default_factory=dict)  #: for :func:`sim.world.make_world` (tests: small textures)

    def out_dir(self) -> Path:
        return Path(self.out) if self.out else default_base_dir()


def render_data(cfg: PretrainConfig) -> Path:
    """Render (or finish rendering) the base's train/val sets; returns data.yaml."""
    from sim.people import CLASS_NAMES
    from sim.trainsets import OrbitSetSpec, render_orbit_split, write_data_yaml

    overlap = set(cfg.train_seeds) & set(cfg.val_seeds)
    if overlap:
        raise ValueError(f"train and val worlds must differ; both contain seeds {sorted(overlap)}")
    data = cfg.out_dir() / "data"
    spec = OrbitSetSpec(altitude_m=cfg.altitude_m, width=cfg.width, height=cfg.height)
    t0 = time.perf_counter()
    n = render_orbit_split(data / "train", cfg.train_seeds, cfg.train_images, 1, spec,
                           world_overrides=cfg.world_overrides)
    n += render_orbit_split(data / "val", cfg.val_seeds, cfg.val_images, 2, spec, world_overrides=cfg.world_overrides)
    log.info("base data: %d views rendered in %.0f s (%s)", n, time.perf_counter() - t0, data)
    return write_data_yaml(data, CLASS_NAMES)


def pretrain_base(cfg: PretrainConfig) -> dict:
    """Render the data if needed, train YOLOv8n from scratch, write ``base.pt`` and ``base.json``."""
    from export.train import TrainConfig, train

    t0 = time.perf_counter()
    out = cfg.out_dir()
    yaml = render_data(cfg)
    render_s = time.perf_counter() - t0
    tcfg = TrainConfig(data=str(yaml), out=str(out / "run"), scale="n", epochs=cfg.epochs, batch=cfg.batch,
                       imgsz=cfg.imgsz, nbs=cfg.nbs, close_mosaic=max(2, cfg.epochs // 5),
                       max_time_s=cfg.budget_s, seed=cfg.seed, threads=cfg.threads, **cfg.extra)
    summary = train(tcfg)
    best = max(summary["history"], key=lambda r: 0.1 * r["map50"] + 0.9 * r["map50_95"])
    tmp = out / "base.pt.tmp"
    shutil.copyfile(summary["best"], tmp)
    os.replace(tmp, out / "base.pt")
    info = {"kind": BASE_KIND, "checkpoint": "base.pt", "config": {k: v for k, v in asdict(cfg).items()
                                                                    if k != "out"},
            "world_seeds": sorted(set(cfg.train_seeds) | set(cfg.val_seeds)),
            "val_map50": best["map50"], "val_map50_95": best["map50_95"], "best_epoch": best.get("epoch"),
            "epochs_run": len(summary["history"]), "render_s": round(render_s, 1),
            "train_s": round(summary.get("seconds", time.perf_counter() - t0 - render_s), 1),
            "written": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    (out / "base.json").write_text(json.dumps(info, indent=1) + "\n")
    log.info("base detector: %s (val mAP50 %.3f, mAP50:95 %.3f)", out / "base.pt", info["val_map50"],
             info["val_map50_95"])
    return info


def find_base(path: str | Path | None = None) -> Path | None:
    """The base checkpoint to fine-tune from: ``path`` (a .pt or a base folder), else the cached one, else None."""
    candidate = Path(path) if path else default_base_dir()
    if candidate.is_dir():
        candidate = candidate / "base.pt"
    if candidate.is_file():
        return candidate
    if path:
        raise FileNotFoundError(f"{path}: no base detector there (make one with `uavsim detector pretrain`)")
    return None


def base_info(checkpoint: str | Path) -> dict:
    """``base.json`` beside a base checkpoint, or {} for a checkpoint from elsewhere."""
    info = Path(checkpoint).with_name("base.json")
    try:
        return json.loads(info.read_text()) if info.is_file() else {}
    except (OSError, json.JSONDecodeError):
        return {}


def check_base_for_world(checkpoint: str | Path, world_seed: int) -> None:
    """Refuse a base trained or validated on the very world being evaluated (a test-set leak)."""
    seeds = base_info(checkpoint).get("world_seeds", [])
    if int(world_seed) in seeds:
        raise ValueError(f"the base detector {checkpoint} was trained on simulator world {world_seed}, the world "
                         f"of this flight: its test numbers would be meaningless; use another --seed")
