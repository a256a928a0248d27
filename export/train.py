"""Training YOLOv8 on a YOLO-format dataset (the published recipe, CPU first, CUDA when present).

Recipe: mosaic (closed for the last ``close_mosaic`` epochs) + random affine + HSV + flips;
task-aligned assigner with CIoU + DFL + BCE losses; optimizer 'auto' = AdamW with
lr = 0.002·5/(4+nc) for short runs (≤ 10k iterations) else SGD lr 0.01, momentum 0.9 — three
parameter groups (conv weights with weight decay, BN weights and biases without); linear warmup
(≥ 100 iterations or ``warmup_epochs``) then cosine decay to ``lrf``·lr; gradient accumulation to a
nominal batch of 64; gradient clipping at 10; EMA of weights (decay 0.9999, ramp τ = 2000 updates).
After every epoch the EMA model is evaluated (mAP, :mod:`export.evaluate`); ``last.pt`` and
``best.pt`` (highest fitness = 0.1·mAP50 + 0.9·mAP50:95) are written to ``out``.

Checkpoint (.pt, a plain dict loadable with ``weights_only=True``): ``model`` (state dict in the
ultralytics key layout), ``scale``, ``nc``, ``names``, ``imgsz``, ``epoch``, ``metrics``.
"""

from __future__ import annotations

import copy
import json
import logging
import math
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from export.dataset import AugmentConfig, YoloDataset, collate, load_data_config
from export.evaluate import evaluate, torch_predictor
from export.loss import DetectionLoss
from export.yolo import YOLOv8

log = logging.getLogger(__name__)


@dataclass
class TrainConfig:
    """What to train and how. Defaults: the paper's fine-tuning (20 epochs, batch 16)."""

    data: str = "data.yaml"
    out: str = "runs/detector"
    scale: str = "n"               #: 'n' or 's'
    weights: str | None = None     #: start from this checkpoint (.pt) instead of scratch
    epochs: int = 20
    batch: int = 16
    imgsz: int = 640
    optimizer: str = "auto"        #: auto | AdamW | SGD
    lr0: float | None = None       #: None: the optimizer's default (auto picks its own)
    lr_scale: float = 1.0          #: multiplies the learning rate chosen above (fine-tuning: 0.1)
    lrf: float = 0.01              #: final lr fraction (cosine)
    momentum: float = 0.937
    weight_decay: float = 5e-4
    nbs: int = 64                  #: nominal batch size (gradient accumulation)
    warmup_epochs: float = 3.0
    warmup_min_iters: int = 100
    warmup_momentum: float = 0.8
    warmup_bias_lr: float = 0.1
    close_mosaic: int = 10
    ema_decay: float = 0.9999
    ema_tau: float = 2000.0
    seed: int = 0
    device: str | None = None      #: None: cuda if available else cpu
    threads: int | None = None     #: torch CPU threads (None: torch default)
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    max_time_s: float | None = None  #: stop after the epoch that crosses this wall-clock budget


def fine_tune_config(**fields) -> TrainConfig:
    """A :class:`TrainConfig` for fine-tuning on one flight's few dozen images (replay, demo, agent).

    The defaults suit thousands of images. On 30-60 images (3-6 batches an epoch) accumulating to the
    nominal batch of 64 leaves one optimizer step per epoch, and a warmup of at least 100 iterations
    outlasts the whole run (20 epochs x 5 batches), so the weights barely leave the base. Here the
    nominal batch is the batch (a step per batch), the warmup one epoch, and the learning rate a tenth
    of the from-scratch one: at full rate a 640 px fine-tune of the demo flight fell from val mAP50 0.81
    to 0.01 in four epochs; at a tenth it rose steadily (bench/RESULTS.md). Explicit ``fields`` win.
    """
    batch = fields.get("batch", TrainConfig.batch)
    return TrainConfig(**{"nbs": batch, "warmup_epochs": 1.0, "warmup_min_iters": 0, "lr_scale": 0.1, **fields})


class ModelEMA:
    """Exponential moving average of the model weights (BN buffers included)."""

    def __init__(self, model: nn.Module, decay: float, tau: float):
        self.ema = copy.deepcopy(model).eval()
        for p in self.ema.parameters():
            p.requires_grad_(False)
        self.decay, self.tau, self.updates = decay, tau, 0

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        self.updates += 1
        d = self.decay * (1 - math.exp(-self.updates / self.tau))
        msd = model.state_dict()
        for k, v in self.ema.state_dict().items():
            if v.dtype.is_floating_point:
                v.mul_(d).add_(msd[k].detach(), alpha=1 - d)


def save_checkpoint(path: Path, model: YOLOv8, imgsz: int, epoch: int, metrics: dict) -> None:
    tmp = path.with_suffix(".tmp")
    torch.save({"model": {k: v.detach().cpu() for k, v in model.state_dict().items()}, "scale": model.scale,
                "nc": model.nc, "names": dict(model.names), "imgsz": imgsz, "epoch": epoch, "metrics": metrics},
               tmp)
    tmp.replace(path)


def load_checkpoint(path: str | Path) -> tuple[YOLOv8, dict]:
    """(model in eval mode on CPU, checkpoint metadata) from a checkpoint written by :func:`save_checkpoint`."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise ValueError(f"cannot read checkpoint {path}: {str(exc).splitlines()[0][:200]}") from exc
    if not isinstance(ckpt, dict) or "model" not in ckpt:
        raise ValueError(f"{path} is not a uavsim detector checkpoint (no 'model' state dict)")
    names = {int(k): str(v) for k, v in ckpt.get("names", {}).items()} or None
    nc = int(ckpt.get("nc") or len(names or {}))
    model = YOLOv8(nc=nc, scale=ckpt.get("scale", "n"), names=names)
    model.load_state_dict(ckpt["model"], strict=True)
    return model.eval(), {k: v for k, v in ckpt.items() if k != "model"}


def build_optimizer(model: nn.Module, cfg: TrainConfig, nc: int, iterations: int):
    """Three param groups (weights with decay; BN weights; biases) and the 'auto' optimizer choice."""
    name, lr, momentum = cfg.optimizer, cfg.lr0, cfg.momentum
    if name == "auto":
        name, lr, momentum = ("SGD", 0.01, 0.9) if iterations > 10000 else ("AdamW", round(0.002 * 5 / (4 + nc), 6),
                                                                             0.9)
        cfg.warmup_bias_lr = 0.0  # a high bias lr is for SGD only
    lr = (lr if lr is not None else (0.01 if name == "SGD" else 0.001)) * cfg.lr_scale
    accumulate = max(round(cfg.nbs / cfg.batch), 1)
    decay = cfg.weight_decay * cfg.batch * accumulate / cfg.nbs
    g_w, g_bn, g_b = [], [], []
    for module in model.modules():
        for pname, p in module.named_parameters(recurse=False):
            if not p.requires_grad:
                continue
            if pname == "bias":
                g_b.append(p)
            elif isinstance(module, nn.BatchNorm2d):
                g_bn.append(p)
            else:
                g_w.append(p)
    if name == "AdamW":
        opt = torch.optim.AdamW(g_b, lr=lr, betas=(momentum, 0.999), weight_decay=0.0)
    elif name == "SGD":
        opt = torch.optim.SGD(g_b, lr=lr, momentum=momentum, nesterov=True)
    else:
        raise ValueError(f"optimizer must be auto, AdamW or SGD, got {name!r}")
    opt.add_param_group({"params": g_w, "weight_decay": decay})
    opt.add_param_group({"params": g_bn, "weight_decay": 0.0})
    log.info("optimizer %s lr=%g momentum=%g, groups: %d weights (decay %.2g), %d bn, %d biases",
             name, lr, momentum, len(g_w), decay, len(g_bn), len(g_b))
    return opt, lr, name


class _Progress:
    """A one-line progress display on interactive terminals; log lines otherwise."""

    def __init__(self):
        self.tty = sys.stderr.isatty()

    def update(self, text: str) -> None:
        if self.tty:
            sys.stderr.write("\r" + text[:150].ljust(150))
            sys.stderr.flush()

    def done(self, text: str) -> None:
        if self.tty:
            sys.stderr.write("\r" + " " * 150 + "\r")
        log.info(text)


def train(cfg: TrainConfig) -> dict:
    """Train; returns a summary with the per-epoch history and the best checkpoint path."""
    t_start = time.perf_counter()
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    device = torch.device(cfg.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    data = load_data_config(cfg.data)
    if not data.train:
        raise ValueError(f"{cfg.data}: no training images")
    if cfg.imgsz % 32 or cfg.imgsz < 32:
        raise ValueError(f"imgsz must be a positive multiple of 32, got {cfg.imgsz}")
    if cfg.epochs < 1 or cfg.batch < 1:
        raise ValueError(f"epochs and batch must be >= 1, got {cfg.epochs}, {cfg.batch}")
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)

    model = YOLOv8(nc=data.nc, scale=cfg.scale, names=data.names)
    model.model[-1].bias_init(cfg.imgsz)
    if cfg.weights:
        src, _ = load_checkpoint(cfg.weights)
        own = model.state_dict()
        loadable = {k: v for k, v in src.state_dict().items() if k in own and own[k].shape == v.shape}
        model.load_state_dict(loadable, strict=False)
        log.info("loaded %d/%d tensors from %s", len(loadable), len(own), cfg.weights)
    model.to(device)

    train_set = YoloDataset(data.train, data.nc, cfg.imgsz, augment=cfg.augment, seed=cfg.seed)
    val_images = data.val or data.train
    if not data.val:
        log.warning("%s has no val split: best checkpoint chosen on training images", cfg.data)
    nb = math.ceil(len(train_set) / cfg.batch)
    accumulate = max(round(cfg.nbs / cfg.batch), 1)
    opt, lr0, opt_name = build_optimizer(model, cfg, data.nc, cfg.epochs * nb)

    def lf(epoch_frac: float) -> float:  # cosine from 1 to lrf
        return ((1 - math.cos(epoch_frac * math.pi / cfg.epochs)) / 2) * (cfg.lrf - 1) + 1

    loss_fn = DetectionLoss(model)
    ema = ModelEMA(model, cfg.ema_decay, cfg.ema_tau)
    nw = max(round(cfg.warmup_epochs * nb), cfg.warmup_min_iters)
    history, best_fit, it, last_step, opt_steps = [], -1.0, 0, -1, 0
    progress = _Progress()
    rng = np.random.default_rng(cfg.seed)
    log.info("training YOLOv8%s on %d images (%d val), %d epochs x %d batches of %d at %d px on %s",
             cfg.scale, len(train_set), len(val_images), cfg.epochs, nb, cfg.batch, cfg.imgsz, device)
    for epoch in range(cfg.epochs):
        model.train()
        if epoch == cfg.epochs - cfg.close_mosaic:
            train_set.augment = AugmentConfig(**{**asdict(cfg.augment), "mosaic": 0.0})
            log.info("epoch %d: mosaic closed", epoch + 1)
        order = rng.permutation(len(train_set))
        t_epoch = time.perf_counter()
        mean_items = torch.zeros(3)
        for bi in range(nb):
            idx = order[bi * cfg.batch:(bi + 1) * cfg.batch]
            imgs, targets = collate([train_set[int(i)] for i in idx])
            imgs = torch.from_numpy(imgs).to(device)
            targets = torch.from_numpy(targets).to(device)
            # warmup: lr ramps from 0 (biases: from warmup_bias_lr) to the schedule; momentum ramps up
            if it <= nw:
                for j, g in enumerate(opt.param_groups):
                    start = cfg.warmup_bias_lr if j == 0 else 0.0
                    g["lr"] = float(np.interp(it, [0, nw], [start, lr0 * lf(epoch)]))
                    mom = float(np.interp(it, [0, nw], [cfg.warmup_momentum, cfg.momentum if opt_name == "SGD"
                                                        else 0.9]))
                    if "betas" in g:
                        g["betas"] = (mom, g["betas"][1])
                    else:
                        g["momentum"] = mom
            loss, items = loss_fn(model(imgs), targets)
            loss.backward()
            if it - last_step >= accumulate or bi == nb - 1:
                nn.utils.clip_grad_norm_(model.parameters(), max_norm=10.0)
                opt.step()
                opt.zero_grad(set_to_none=True)
                ema.update(model)
                last_step = it
                opt_steps += 1
            it += 1
            mean_items = (mean_items * bi + items.cpu()) / (bi + 1)
            progress.update(f"epoch {epoch + 1}/{cfg.epochs} batch {bi + 1}/{nb} box {mean_items[0]:.3f} "
                            f"cls {mean_items[1]:.3f} dfl {mean_items[2]:.3f} "
                            f"{(time.perf_counter() - t_epoch) / (bi + 1):.2f} s/batch")
        if it > nw:
            for g in opt.param_groups:
                g["lr"] = lr0 * lf(epoch + 1)
        train_s = time.perf_counter() - t_epoch
        res = evaluate(torch_predictor(ema.ema, cfg.imgsz), val_images, data.names)
        fit = 0.1 * res.map50 + 0.9 * res.map50_95
        row = {"epoch": epoch + 1, "box": float(mean_items[0]), "cls": float(mean_items[1]),
               "dfl": float(mean_items[2]), "map50": res.map50, "map50_95": res.map50_95,
               "train_s": train_s, "elapsed_s": time.perf_counter() - t_start,
               "lr": opt.param_groups[1]["lr"], "optimizer_steps": opt_steps}
        history.append(row)
        metrics = {"map50": res.map50, "map50_95": res.map50_95, "per_class": res.per_class}
        save_checkpoint(out / "last.pt", ema.ema, cfg.imgsz, epoch + 1, metrics)
        if fit > best_fit:
            best_fit = fit
            save_checkpoint(out / "best.pt", ema.ema, cfg.imgsz, epoch + 1, metrics)
        progress.done(f"epoch {epoch + 1}/{cfg.epochs}: loss box {row['box']:.3f} cls {row['cls']:.3f} "
                      f"dfl {row['dfl']:.3f}  val mAP50 {res.map50:.4f} mAP50:95 {res.map50_95:.4f}  "
                      f"({train_s:.0f} s train, {row['elapsed_s']:.0f} s total)")
        (out / "history.json").write_text(json.dumps(history, indent=1) + "\n")
        if cfg.max_time_s and time.perf_counter() - t_start > cfg.max_time_s:
            log.warning("time budget %.0f s reached after epoch %d", cfg.max_time_s, epoch + 1)
            break
    best = max(history, key=lambda r: 0.1 * r["map50"] + 0.9 * r["map50_95"])
    return {"best": str(out / "best.pt"), "last": str(out / "last.pt"), "best_epoch": best["epoch"],
            "map50": best["map50"], "map50_95": best["map50_95"], "history": history,
            "seconds": time.perf_counter() - t_start, "optimizer": opt_name, "lr0": lr0, "optimizer_steps": opt_steps}
