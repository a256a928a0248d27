"""Fitting a static model to a flight: rays across frames, Adam with a decaying schedule, a wall-clock
budget and/or an iteration count, held-out evaluation, checkpoint and resume.

Losses: MSE on RGB (over box-oversampled batches plain, so it leans to people, or importance-weighted:
``rgb_importance_weighted``); ``lambda_dist`` x the distortion loss (pulls each ray's weight onto one surface,
the main defence against floaters that show up at higher altitudes); ``lambda_mask`` x the
negative log-likelihood of the frame's filled-box class at the pixel (people cover ~1 % of a frame,
so ``mask_pos_fraction`` of each batch is drawn from box pixels, importance-weighted so the loss
stays unbiased: a ground point inside a person's box in few views must stay background; an extra
``mask_fg_weight`` on box pixels biases that and grows the blobs); ``lambda_empty`` x the mean
density of random points in the upper part of the slab that no training ray saw as opaque (a weak
prior that air is empty unless the images say otherwise); ``lambda_topdown`` x the distortion loss
of virtual rays looking down from above the box (off by default; see :class:`FitConfig`).

Optionally (``mask_phase_share``) the last part of the budget trains only the mask on the frozen
geometry, from the cached live samples of a fixed set of rays (:class:`_MaskCache`).
"""

from __future__ import annotations

import json
import logging
import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from fields.data import FlightData, RayBank
from fields.description_diff import description_differences
from fields.evaluation import label_boxes, match_boxes, psnr, ssim
from fields.field import FieldConfig
from fields.footprint import footprint_map
from fields.mask_boxes import BoxRules, boxes_from_probabilities
from fields.model import SamplerConfig, StaticModel, topdown_rays
from fields.scene import SceneBounds, Sizing, hash_params, scene_bounds, size_model

log = logging.getLogger(__name__)

CHECKPOINT = "static.pt"
#: share of ``budget_mb`` set aside for the mask's own hash grid (``mask_encoding="grid"``)
MASK_BUDGET_SHARE = 0.2


@dataclass
class FitConfig:
    """Training options; defaults = the measured default of ``uavsim fit`` (see bench/RESULTS.md)."""

    encoding: str = "hash"
    #: "occupancy" beat "stratified" at 300 s on 2 cores: +0.57 dB held-out, box IoU 0.767 vs 0.727, level at
    #: 35 / 50 m; synthesis renders 1.4-1.9x slower (bench/RESULTS.md, static fields session 10)
    sampler: str = "occupancy"
    n_samples: int = 32
    #: stop after this many iterations ...
    iters: int = 20000
    #: ... or this many seconds of training (None: no time limit)
    budget_s: float | None = 300.0
    batch_rays: int = 1024
    lr: float = 1e-2
    #: the MLPs' learning rate relative to ``lr`` (the encoding and background use ``lr``)
    mlp_lr_scale: float = 1.0
    #: learning rate at the end of the run, as a fraction of ``lr`` (exponential decay); 0.3 beat 0.1 at
    #: 300 s by +1.3 dB held-out and +0.14 mask box IoU in a paired run (bench/RESULTS.md, session 6)
    lr_final: float = 0.3
    holdout_every: int = 8
    seed: int = 0
    #: CPU threads (None: torch's default)
    threads: int | None = None
    budget_mb: float = 20.0
    features: int | None = None
    view_dependent: bool = False
    appearance_dim: int = 8
    hidden: int = 64
    lambda_dist: float = 2e-3
    lambda_mask: float = 0.05
    mask_fg_weight: float = 1.0
    #: background probability of the fresh mask head (None: torch's default, ~uniform; see FieldConfig)
    mask_init_background: float | None = None
    #: learning rate of the mask's grid and head relative to ``lr`` (their own Adam group when != 1)
    mask_lr_scale: float = 1.0
    #: "grid" (the mask's own small hash grid) or "geometry" (a head on the detached geometry features)
    mask_encoding: str = "grid"
    mask_log2_table: int = 16
    #: share of each ray batch drawn from pixels inside label boxes (0: uniform over all pixels). 0.25 with
    #: ``rgb_importance_weighted`` against 0 at 300 s on 2 cores, four runs: held-out mask box IoU 0.856-0.861 at
    #: the calibrated cut against 0.765-0.805, synthesis recall and precision 1.0 at 35 and 50 m; the price is
    #: 0.4-0.8 dB at 50 m (25.16-25.25 against 25.61-26.01 dB) (bench/RESULTS.md, static session 35)
    mask_pos_fraction: float = 0.25
    #: with ``mask_pos_fraction`` > 0, the RGB loss is importance-weighted like the mask loss (True: the
    #: colour fit sees every pixel equally) or plain (False: it leans to the people the extra box rays hit,
    #: measured -1.0 to -1.5 dB at 50 m for the same box IoU)
    rgb_importance_weighted: bool = True
    #: box rays (``mask_pos_fraction``) are drawn until this share of the main training (by seconds, or by
    #: steps without a budget) has passed; after it every ray is uniform (1: throughout). At 0.5, one run at 300 s
    #: on 2 cores: 50 m 25.42 dB, box IoU 0.813 (0.827 at the calibrated cut), between ``mask_pos_fraction`` 0.1
    #: and the default on both (bench/RESULTS.md, static session 36)
    mask_pos_until: float = 1.0
    #: a box pixel with under 10 % of its rendering weight (current geometry, no gradient) higher than
    #: this above the ground sees the ground around the person, not the person: it is taught as
    #: background (None: every box pixel is the box's class, the paper's filled boxes)
    mask_box_min_height_m: float | None = None
    #: share of the budget (seconds; iterations without a budget) for a last phase that trains only
    #: the mask on the frozen geometry: the live samples of ``mask_phase_rays`` rays are computed once,
    #: then minibatches train the mask grid and head on them (measured not to help at 60 s: RESULTS.md)
    mask_phase_share: float = 0.0
    #: also train the mask during the RGB phase (with a mask phase; without one it always trains there)
    mask_joint: bool = True
    #: rays whose live samples the mask phase computes once (the costly part), and its minibatch
    mask_phase_rays: int = 32768
    mask_phase_batch_rays: int = 4096
    #: share of the mask phase's rays drawn inside label boxes (importance-weighted, unbiased)
    mask_phase_pos_fraction: float = 0.25
    mask_phase_lr: float = 1e-2
    lambda_empty: float = 0.0
    #: ``lambda_topdown`` x the distortion loss of ``topdown_ray_count`` rays per step that look down into the box
    #: from above, within ``topdown_tilt_deg`` of nadir, from step ``topdown_start`` on: a prior against the
    #: density that floats metres above the ground where the cameras saw it only at grazing angles, which a
    #: higher view exposes. At 5e-3 it removed most of those floaters but moved 50 m PSNR by -0.04 dB and cost
    #: 1.1 dB held-out at 300 s (bench/RESULTS.md, static session 13); 0: off
    lambda_topdown: float = 0.0
    topdown_ray_count: int = 256
    topdown_tilt_deg: float = 30.0
    topdown_start: int = 200
    occupancy_every: int = 16
    occupancy_warmup: int = 200
    #: occupancy grid cell (x, y, z metres; at most 256 cells per axis)
    occupancy_cell_m: tuple[float, float, float] = (0.5, 0.5, 0.25)
    checkpoint_every_s: float = 60.0
    log_every_s: float = 10.0
    #: cell size multiplier over the finest GSD (1 = as fine as the data)
    cell_factor: float = 1.0
    #: metres added around the training rays' ground hits (:func:`fields.scene.scene_bounds`)
    box_margin_m: float = 2.0
    #: the box spans this percentile of the training rays' ground hits (and 100 minus it) before the margin;
    #: 100: every ground point a training ray saw within reach. Against 98 (the default until session 15; the box
    #: then ended where the 50 m views still see trees and buildings, drawn on the flat background texture),
    #: 100 gained +0.9-1.4 dB at 35 m and +1.0-1.3 dB at 50 m at 300 s (two runs against four), lost up to 0.7 dB
    #: under the orbit and 0.02-0.04 box IoU (the same hash table over 2.7x the area), level held-out; 17.2 MB
    #: against 15.8 (bench/RESULTS.md, static session 15)
    box_coverage_pct: float = 100.0
    #: metres from the ground estimate down to the box's floor, where rays that reach it end opaque (None: 5 % of
    #: the box's height, at least 0.5 m, the rule until session 34 and still the dynamic fit's). The orbit sees the
    #: ground beyond it only at grazing angles and the field leaves it as faint fog, so a view from above sees mostly
    #: this floor there; 0.5 m down, the grazing rays had painted it 1.7 m from where they looked. 0.1 m gained
    #: +2.9 / +3.2 dB at 50 m and +3.2 / +3.4 dB at 35 m against the old floor, for -0.4 / -0.3 dB held-out at 15 m
    #: (300 s, two pairs; bench/RESULTS.md, static session 34). The ground estimate is the take-off point without
    #: SfM points (a flat site) or the 5th percentile of their heights: terrain below the floor renders at the floor
    box_floor_margin_m: float | None = 0.1
    #: texels per side of the background ground texture (beyond the slab; contracted, inner disc = half)
    background_resolution: int = 64
    #: footprint-aware background lookup (a learned mip map, :class:`fields.field.Background`); needs a
    #: power-of-two ``background_resolution``. At 256 / 512 texels it scored 0.1-0.8 dB *below* the plain 64²
    #: texture outside the box at 50 m (300 s; bench/RESULTS.md, static session 14): the error there is the
    #: parallax of trees and buildings on a flat texture, not its resolution. Off
    background_mip: bool = False
    #: damp each hash level where the training frames saw the ground coarser than its cells (a map of
    #: the finest footprint over ``footprint_cells`` x ``footprint_cells`` xy cells of the box;
    #: :mod:`fields.footprint`); False: every level at full weight everywhere. One paired 300 s run: level at
    #: every altitude (held-out 34.79 vs 34.99, 35 m 26.40 vs 26.39, 50 m 22.98 vs 23.03 dB), mask box IoU 0.763
    #: vs 0.799 (bench/RESULTS.md, static session 16). Off
    level_footprint: bool = False
    footprint_cells: int = 64


@dataclass
class FitResult:
    model: StaticModel
    step: int
    train_s: float
    curve: list[dict] = field(default_factory=list)
    bounds: SceneBounds | None = None
    sizing: Sizing | None = None
    #: steps of the mask-only phase (included in ``step``)
    mask_steps: int = 0
    #: a resumed fit: ``{description path: (checkpoint's value, the options' value)}`` where the options
    #: asked for a different model than the checkpoint holds (:func:`model_the_checkpoint_keeps`)
    resume_kept: dict = field(default_factory=dict)


def device() -> torch.device:
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def configure_threads(threads: int | None) -> None:
    """Set torch's CPU threads; ``OMP_WAIT_POLICY=PASSIVE`` must be in the environment before torch
    loads (the CLI sets it) or idle OpenMP threads spin and slow a shared machine 2-13x."""
    if os.environ.get("OMP_WAIT_POLICY", "").upper() != "PASSIVE":
        log.warning("OMP_WAIT_POLICY is not PASSIVE: CPU training may be much slower on a busy machine")
    if threads:
        torch.set_num_threads(int(threads))


def build_model(data: FlightData, train_idx: list[int], cfg: FitConfig, flight: Path | None) -> tuple:
    """Bounds, sizing and a fresh model for the training frames."""
    Ts = [data.cam_from_world[i] for i in train_idx]
    bounds = scene_bounds(flight, data.camera, Ts, margin_m=cfg.box_margin_m,
                          coverage_pct=cfg.box_coverage_pct, floor_margin_m=cfg.box_floor_margin_m)
    geo_mb = cfg.budget_mb * (1.0 - MASK_BUDGET_SHARE if cfg.mask_encoding == "grid" else 1.0)
    sizing = size_model(bounds, cfg.encoding, geo_mb, cfg.features, cell_factor=cfg.cell_factor)
    mask_res, mask_log2 = _mask_grid(bounds, cfg, geo_mb, sizing)
    fc = FieldConfig(aabb_lo=bounds.lo, aabb_hi=bounds.hi, encoding=sizing.encoding,
                     resolutions=sizing.resolutions, features=sizing.features, log2_table=sizing.log2_table,
                     hidden=cfg.hidden, n_images=data.n, appearance_dim=cfg.appearance_dim,
                     view_dependent=cfg.view_dependent, n_classes=len(data.classes),
                     mask_encoding=cfg.mask_encoding, mask_resolutions=mask_res, mask_log2_table=mask_log2,
                     mask_init_background=cfg.mask_init_background,
                     footprint_cells=(cfg.footprint_cells,) * 2 if cfg.level_footprint else None)
    ext = np.asarray(bounds.extent)
    grid = tuple(int(min(256, max(8, math.ceil(e / c)))) for e, c in zip(ext, cfg.occupancy_cell_m, strict=True))
    sc = SamplerConfig(cfg.sampler, cfg.n_samples, 96, grid)
    radius = 0.5 * float(np.hypot(ext[0], ext[1]))
    model = StaticModel(fc, sc, bounds.ground_z, radius, cfg.background_resolution, cfg.background_mip)
    if cfg.level_footprint:
        fp = footprint_map(data.camera, Ts, bounds.lo[:2], bounds.hi[:2], bounds.ground_z, fc.footprint_cells)
        model.field.set_footprint(fp)
        sizing.reasoning.append(f"level footprint map {fc.footprint_cells[0]}x{fc.footprint_cells[1]} cells: finest "
                                f"footprint {fp.min() * 100:.1f} cm (median {np.median(fp) * 100:.1f}, max "
                                f"{fp.max() * 100:.1f}); levels finer than the data there are damped")
    return model, bounds, sizing


def model_the_checkpoint_keeps(saved: dict, data: FlightData, train_idx: list[int], cfg: FitConfig,
                               flight: Path | None) -> dict[str, tuple]:
    """Where a checkpoint's model description (``saved``) differs from that of the model ``cfg`` would
    build for this flight: ``{path: (saved, fresh)}`` (:func:`fields.description_diff.description_differences`).

    A resumed fit keeps the checkpoint's model, so these are the options' effects that do not apply. The
    model is built on the CPU under a forked random state, so the resumed run draws what it would have."""
    with torch.random.fork_rng(devices=[]):
        fresh, _, _ = build_model(data, train_idx, cfg, flight)
    return description_differences(saved, fresh.describe())


def _mask_grid(bounds: SceneBounds, cfg: FitConfig, geo_mb: float, sizing: Sizing) -> tuple[list, int]:
    """The mask grid's levels (every second level of a hash sizing of the scene, ending at the finest)
    and table size (``mask_log2_table``, halved until it fits ``MASK_BUDGET_SHARE`` of the budget)."""
    res = size_model(bounds, "hash", geo_mb, cell_factor=cfg.cell_factor).resolutions[::-2][::-1]
    log2 = cfg.mask_log2_table
    budget = cfg.budget_mb * MASK_BUDGET_SHARE * 1e6 / 4
    while log2 > 8 and hash_params(res, 2, log2) > budget:
        log2 -= 1
    if cfg.mask_encoding == "grid":
        sizing.reasoning.append(f"mask grid: {len(res)} levels (every second, to the finest), table 2^{log2} x 2 "
                                f"features, within {MASK_BUDGET_SHARE:.0%} of the {cfg.budget_mb:g} MB budget")
    return res, log2


def _optimizer(model: StaticModel, cfg: FitConfig):
    enc = list(model.field.encoding.parameters()) + list(model.background.parameters())
    mask = list(model.field.mask_head.parameters())
    if model.field.mask_grid is not None:
        mask += list(model.field.mask_grid.parameters())
    if cfg.mask_lr_scale == 1.0:  # the mask grid with the encodings, its head with the MLPs
        enc += mask[len(list(model.field.mask_head.parameters())):]
        mask = []
    taken = {id(p) for p in enc + mask}
    rest = [p for p in model.parameters() if id(p) not in taken]
    groups = [{"params": enc, "lr": cfg.lr, "eps": 1e-15, "scale": 1.0},
              {"params": rest, "lr": cfg.lr * cfg.mlp_lr_scale, "eps": 1e-15, "scale": cfg.mlp_lr_scale}]
    if mask:
        groups.append({"params": mask, "lr": cfg.lr * cfg.mask_lr_scale, "eps": 1e-15, "scale": cfg.mask_lr_scale})
    try:
        return torch.optim.Adam(groups, lr=cfg.lr, betas=(0.9, 0.99), fused=True)
    except (RuntimeError, TypeError):  # older torch without fused CPU Adam
        return torch.optim.Adam(groups, lr=cfg.lr, betas=(0.9, 0.99))


def save_checkpoint(path: Path, model: StaticModel, optim, step: int, train_s: float, cfg: FitConfig,
                    extra: dict) -> None:
    """Atomic write (temp + rename): a crash never leaves half a checkpoint."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"format": "uavsim-static-1", "model": model.describe(), "state": model.state_dict(),
                "sampler_state": model.sampler.state_dict(), "optim": optim.state_dict() if optim else None,
                "step": step, "train_s": train_s, "fit_config": asdict(cfg), **extra}, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: str | Path, map_location=None) -> tuple[StaticModel, dict]:
    """The model (eval mode) and the raw checkpoint dict."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no fitted field (run 'uavsim fit' first)")
    ck = torch.load(path, map_location=map_location or device(), weights_only=False)
    if ck.get("format") != "uavsim-static-1":
        raise ValueError(f"{path}: not a uavsim static field checkpoint")
    model = StaticModel.from_description(ck["model"])
    model.load_state_dict(ck["state"])
    model.sampler.load_state_dict(ck["sampler_state"])
    if hasattr(model.sampler, "to"):
        model.sampler.to(map_location or device())
    return model.to(map_location or device()).eval(), ck


def upper_box_points(lo: torch.Tensor, hi: torch.Tensor, n: int, above: float,
                     generator: torch.Generator) -> torch.Tensor:
    """``n`` points (n, 3) uniform in the box ``lo``..``hi`` (world ENU, m) above the share ``above``
    of its height: where the air-density priors look for density the images did not ask for."""
    u = torch.rand(n, 3, device=lo.device, generator=generator)
    u[:, 2] = above + (1.0 - above) * u[:, 2]
    return lo + u * (hi - lo)


def schedule_progress(step: int, iters: int, train_s: float, budget_s: float | None) -> float:
    """Fraction of training done, 0..1: by steps, or by seconds when a budget is set (whichever is further)."""
    p = step / max(iters, 1)
    if budget_s:
        p = max(p, train_s / budget_s)
    return min(p, 1.0)


def fit(data: FlightData, cfg: FitConfig, out_dir: Path | None = None, flight: Path | None = None,
        resume: bool = False, on_eval: Callable | None = None, eval_at_s: list[float] | None = None,
        eval_at_iters: list[int] | None = None) -> FitResult:
    """Train a static model. ``on_eval(model, step, train_s)`` is called at the listed training
    seconds / iterations (its own time is not counted). Checkpoints go to ``out_dir/static.pt``."""
    configure_threads(cfg.threads)
    dev = device()
    torch.manual_seed(cfg.seed)
    gen = torch.Generator(device=dev).manual_seed(cfg.seed)
    train_idx, _ = data.split(cfg.holdout_every)
    if not train_idx:
        raise ValueError("no training frames left after holding out every "
                         f"{cfg.holdout_every}th frame of {data.n}")
    ckpt = out_dir / CHECKPOINT if out_dir else None
    kept: dict[str, tuple] = {}
    if resume and ckpt and ckpt.is_file():
        model, ck = load_checkpoint(ckpt, dev)
        kept = model_the_checkpoint_keeps(ck["model"], data, train_idx, cfg, flight)
        if kept:
            log.warning("resuming %s: the model keeps the checkpoint's shape, so options that would change it "
                        "apply only to a fresh fit (drop --resume to start over); checkpoint -> these options: %s",
                        ckpt, "; ".join(f"{k}: {old!r} -> {new!r}" for k, (old, new) in kept.items()))
        model.train()
        optim = _optimizer(model, cfg)
        if ck.get("optim"):
            optim.load_state_dict(ck["optim"])
        step, train_s = int(ck["step"]), float(ck["train_s"])
        bounds = SceneBounds(**ck["bounds"]) if ck.get("bounds") else None
        sizing = Sizing(**ck["sizing"]) if ck.get("sizing") else None
        curve = list(ck.get("curve", []))
        if "rng" in ck:
            gen.set_state(ck["rng"])
        log.info("resumed from %s at step %d (%.0f s)", ckpt, step, train_s)
    else:
        model, bounds, sizing = build_model(data, train_idx, cfg, flight)
        model = model.to(dev)
        if hasattr(model.sampler, "to"):
            model.sampler.to(dev)
        optim = _optimizer(model, cfg)
        step, train_s, curve = 0, 0.0, []
    model.train()
    log.info("model: %s encoding, %d parameters (%.1f MB), sampler %s", model.field_config.encoding,
             model.param_count(), model.param_count() * 4 / 1e6, model.sampler_config.kind)

    bank = RayBank(data.camera, data.cam_from_world, dev)
    images = data.images.to(dev).view(data.n, -1, 3)
    masks = data.masks.to(dev).view(data.n, -1).long()
    has_mask = data.has_mask.to(dev)
    train_t = torch.tensor(train_idx, device=dev)
    hw = bank.hw
    use_amp = dev.type == "cuda"
    scaler = torch.amp.GradScaler("cuda") if use_amp else None
    fg_w = torch.ones(len(data.classes) + 1, device=dev)
    fg_w[1:] = cfg.mask_fg_weight
    pos_frame, pos_pixel = positive_pixels(masks, has_mask, train_t)
    mask_frames = train_t[has_mask[train_t]]
    # the mask-only phase: the last ``mask_phase_share`` of the budget (seconds, or iterations without one)
    share = cfg.mask_phase_share if cfg.lambda_mask > 0 and len(mask_frames) else 0.0
    main_iters = cfg.iters - int(round(share * cfg.iters)) if not cfg.budget_s else cfg.iters
    main_budget = cfg.budget_s * (1.0 - share) if cfg.budget_s else None
    joint_mask = cfg.lambda_mask > 0 and (cfg.mask_joint or share == 0)
    n_pos = int(round(cfg.mask_pos_fraction * cfg.batch_rays)) if joint_mask and len(pos_frame) else 0
    iw = importance_weights(cfg.batch_rays, n_pos, len(train_idx) * hw, len(pos_frame), dev)
    iw_uniform = importance_weights(cfg.batch_rays, 0, len(train_idx) * hw, len(pos_frame), dev)  # after mask_pos_until
    evals_s = sorted(eval_at_s or [])
    evals_i = sorted(eval_at_iters or [])

    def progress() -> float:
        return schedule_progress(step, main_iters, train_s, main_budget)

    def draw(frames: torch.Tensor, n: int, n_box: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(frame, pixel) of ``n`` rays: uniform over ``frames``, then ``n_box`` of them inside label boxes."""
        fi = frames[torch.randint(len(frames), (n - n_box,), device=dev, generator=gen)]
        pi = torch.randint(hw, (n - n_box,), device=dev, generator=gen)
        if n_box:  # oversampled pixels inside label boxes (people cover ~1 % of a frame)
            k = torch.randint(len(pos_frame), (n_box,), device=dev, generator=gen)
            fi, pi = torch.cat([fi, pos_frame[k]]), torch.cat([pi, pos_pixel[k]])
        return fi, pi

    last_log = last_ckpt = 0.0
    interactive = sys.stderr.isatty()
    t_mark = time.perf_counter()
    loss_ema = None

    def after_step(loss_value: float, lr: float, phase: str) -> None:
        """Count the step and its time; log, call the evaluation hook and checkpoint when due."""
        nonlocal step, train_s, t_mark, last_log, last_ckpt, loss_ema
        step += 1
        now = time.perf_counter()
        train_s += now - t_mark
        t_mark = now
        loss_ema = loss_value if loss_ema is None else 0.95 * loss_ema + 0.05 * loss_value
        if train_s - last_log >= cfg.log_every_s:
            last_log = train_s
            if phase == "rgb":
                p = -10 * math.log10(max(loss_ema, 1e-10))
                curve.append({"step": step, "train_s": round(train_s, 2), "train_psnr": round(p, 2), "lr": lr})
                msg = f"step {step} {train_s:.0f}s train PSNR {p:.2f} dB lr {lr:.2e}"
            else:
                curve.append({"step": step, "train_s": round(train_s, 2), "mask_nll": round(loss_ema, 4), "lr": lr})
                msg = f"step {step} {train_s:.0f}s mask phase NLL {loss_ema:.4f} lr {lr:.2e}"
            if interactive:
                print(f"\r{msg}   ", end="", file=sys.stderr, flush=True)
            log.info(msg)
        hook = False
        while evals_s and train_s >= evals_s[0]:
            evals_s.pop(0)
            hook = True
        while evals_i and step >= evals_i[0]:
            evals_i.pop(0)
            hook = True
        if hook and on_eval:
            mode = model.training
            model.eval()
            on_eval(model, step, train_s)
            model.train(mode)
            t_mark = time.perf_counter()
        if ckpt and train_s - last_ckpt >= cfg.checkpoint_every_s:
            last_ckpt = train_s
            save_checkpoint(ckpt, model, optim, step, train_s, cfg, _extra(bounds, sizing, curve, gen))
            t_mark = time.perf_counter()

    occupancy = model.sampler_config.kind == "occupancy"  # the model's: a resume may have asked for another
    while step < main_iters and (main_budget is None or train_s < main_budget):
        done = progress()
        lr = cfg.lr * cfg.lr_final ** done
        for g in optim.param_groups:
            g["lr"] = lr * g.get("scale", 1.0)
        box_rays = n_pos if done < cfg.mask_pos_until else 0
        fi, pi = draw(train_t, cfg.batch_rays, box_rays)
        o, d = bank.rays(fi, pi)
        target = images[fi, pi].float() / 255.0
        boxed = masks[fi, pi]
        # importance weights follow how each ray was drawn (inside a box or not)
        ray_w = (iw if box_rays else iw_uniform)[(boxed > 0).long()]
        with torch.autocast("cuda", dtype=torch.float16, enabled=use_amp):
            res = model.render_rays(o, d, fi, train=True, generator=gen, with_mask=joint_mask,
                                    pixel_rad=data.camera.pixel_rad)
            loss_rgb = rgb_mse(res["rgb"], target, ray_w if cfg.rgb_importance_weighted else None)
            loss = loss_rgb
            if cfg.lambda_dist > 0:
                loss = loss + cfg.lambda_dist * model.distortion(res)
            if joint_mask:
                m_ok = has_mask[fi]
                if m_ok.any():
                    tgt = boxed
                    if cfg.mask_box_min_height_m is not None:
                        tgt = ground_in_box_as_background(boxed, res["weights"].detach(), res["sample_z"],
                                                          model.background.ground_z, cfg.mask_box_min_height_m)
                    tgt = tgt[m_ok]
                    loss = loss + cfg.lambda_mask * _mask_nll(res["mask_probs"][m_ok], tgt, fg_w[tgt] * ray_w[m_ok])
            if cfg.lambda_empty > 0:
                air = upper_box_points(model.field.lo, model.field.hi, 4096, 0.3, gen)  # upper 70 % of the slab
                loss = loss + cfg.lambda_empty * model.field.density(air).clamp_max(10).mean()
            if cfg.lambda_topdown > 0 and step >= cfg.topdown_start:
                o_v, d_v = topdown_rays(model.field.lo, model.field.hi, cfg.topdown_ray_count, cfg.topdown_tilt_deg,
                                       gen)
                loss = loss + cfg.lambda_topdown * model.geometry_distortion(o_v, d_v, gen)
        optim.zero_grad(set_to_none=True)
        if scaler:
            scaler.scale(loss).backward()
            scaler.step(optim)
            scaler.update()
        else:
            loss.backward()
            optim.step()
        if occupancy and step + 1 >= cfg.occupancy_warmup and (step + 1) % cfg.occupancy_every == 0:
            model.sampler.update(model.field.density, model.field.lo, model.field.hi, generator=gen)
        after_step(float(loss_rgb.detach()), lr, "rgb")

    mask_steps = 0
    if share > 0 and step < cfg.iters and (cfg.budget_s is None or train_s < cfg.budget_s):
        # mask only, on the frozen geometry: the live samples of a fixed set of rays are computed
        # once (the costly part: density at every sample), then the mask trains on them for the rest
        model.eval()
        n_box = int(round(cfg.mask_phase_pos_fraction * cfg.mask_phase_rays)) if len(pos_frame) else 0
        fi, pi = draw(mask_frames, cfg.mask_phase_rays, n_box)
        cache = _MaskCache(model, bank, fi, pi, masks,
                           importance_weights(cfg.mask_phase_rays, n_box, len(mask_frames) * hw, len(pos_frame), dev),
                           fg_w)
        params = list(model.field.mask_head.parameters())
        params += list(model.field.mask_grid.parameters()) if model.field.mask_grid is not None else []
        mask_optim = torch.optim.Adam(params, lr=cfg.mask_phase_lr, betas=(0.9, 0.99), eps=1e-15)
        now = time.perf_counter()
        train_s, t_mark = train_s + now - t_mark, now  # the cache's time counts as training
        step0, s0 = step, train_s
        loss_ema = None
        while step < cfg.iters and (cfg.budget_s is None or train_s < cfg.budget_s):
            done = (train_s - s0) / max(cfg.budget_s - s0, 1e-9) if cfg.budget_s else \
                (step - step0) / max(cfg.iters - step0, 1)
            lr = cfg.mask_phase_lr * cfg.lr_final ** min(done, 1.0)
            for g in mask_optim.param_groups:
                g["lr"] = lr
            loss = cache.loss(model, cfg.mask_phase_batch_rays, gen)
            mask_optim.zero_grad(set_to_none=True)
            loss.backward()
            mask_optim.step()
            after_step(float(loss.detach()), lr, "mask")
        mask_steps = step - step0
    if interactive:
        print(file=sys.stderr)
    model.eval()
    if ckpt:
        save_checkpoint(ckpt, model, optim, step, train_s, cfg, _extra(bounds, sizing, curve, gen))
    return FitResult(model, step, train_s, curve, bounds, sizing, mask_steps, kept)


class _MaskCache:
    """Rays for the mask-only phase with their live samples on the frozen geometry (computed once, in
    chunks), targets and loss weights; :meth:`loss` draws a minibatch of rays and composites their mask."""

    def __init__(self, model: StaticModel, bank: RayBank, fi: torch.Tensor, pi: torch.Tensor,
                 masks: torch.Tensor, iw: torch.Tensor, fg_w: torch.Tensor, chunk: int = 4096):
        parts = []
        for a in range(0, len(fi), chunk):
            o, d = bank.rays(fi[a:a + chunk], pi[a:a + chunk])
            ray, w, pts, geo, rest = model.mask_samples(o, d)
            parts.append((ray + a, w, pts, geo, rest))
        self.ray, self.w, self.pts, self.geo, self.rest = (torch.cat(p) for p in zip(*parts, strict=True))
        self.target = masks[fi, pi]
        # importance weights by label: a box pixel can be drawn uniformly or from the boxes
        self.weight = fg_w[self.target] * iw[(self.target > 0).long()]
        order = torch.argsort(self.ray, stable=True)
        self.ray, self.w, self.pts, self.geo = self.ray[order], self.w[order], self.pts[order], self.geo[order]
        self.start = torch.searchsorted(self.ray, torch.arange(len(fi) + 1, device=self.ray.device))

    def probs(self, model: StaticModel, rays: torch.Tensor) -> torch.Tensor:
        """Composited class probabilities (len(rays), C+1) of the cached rays ``rays`` (indices)."""
        counts = self.start[rays + 1] - self.start[rays]
        local = torch.repeat_interleave(torch.arange(len(rays), device=rays.device), counts)  # sample -> batch ray
        first = counts.cumsum(0) - counts  # each batch ray's first sample in the gathered order
        idx = self.start[rays][local] + torch.arange(len(local), device=rays.device) - first[local]
        return model.composite_mask(local, self.w[idx], self.pts[idx], self.geo[idx], self.rest[rays])

    def loss(self, model: StaticModel, batch: int, gen) -> torch.Tensor:
        """Weighted mask NLL of ``batch`` cached rays drawn without replacement."""
        rays = torch.randperm(len(self.target), device=self.ray.device, generator=gen)[:batch]
        return _mask_nll(self.probs(model, rays), self.target[rays], self.weight[rays])


def importance_weights(batch: int, n_box: int, n_all: int, n_pos: int, dev) -> torch.Tensor:
    """Loss weights (background pixel, box pixel) that keep the mask loss unbiased when ``n_box`` of
    ``batch`` rays are drawn from the ``n_pos`` box pixels and the rest uniformly from ``n_all``
    pixels: the mixture draws a box pixel with probability (B_u/B)/N + (B_p/B)/N_pos, a background
    one (B_u/B)/N."""
    n_uni = batch - n_box
    return torch.tensor([batch / n_uni, batch / (n_uni + n_box * n_all / max(n_pos, 1))], device=dev)


def ground_in_box_as_background(target: torch.Tensor, weights: torch.Tensor, sample_z: torch.Tensor,
                                ground_z: float, min_height_m: float, min_share: float = 0.1) -> torch.Tensor:
    """Class targets (R,) with box pixels (class > 0) that see (almost) only ground set to background (0).

    A filled box also covers the ground beside and behind its person, and each view's box covers
    different ground, so the mask would learn a halo around the feet. A box pixel counts as ground
    when less than ``min_share`` of its rendering weight (``weights`` (R, S), no gradient needed) lies
    at samples higher than ``min_height_m`` above ``ground_z`` (``sample_z`` (R, S), ENU metres). A
    share, not the expected depth: a pixel half on a head and half on far ground stays the person's."""
    above = (weights * (sample_z > ground_z + min_height_m)).sum(-1)
    on_ground = torch.isfinite(above) & (above < min_share)
    return torch.where((target > 0) & on_ground, torch.zeros_like(target), target)


def rgb_mse(rgb: torch.Tensor, target: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
    """Mean squared colour error of rays (R, 3); with ``weights`` (R,) each ray's mean over its channels is
    weighted (importance weights: :func:`importance_weights`), so the batch mean stays unbiased."""
    if weights is None:
        return torch.mean((rgb - target) ** 2)
    return torch.mean(((rgb - target) ** 2).mean(-1) * weights)


def _mask_nll(probs: torch.Tensor, target: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Weighted mean negative log-likelihood of the target classes (R,) under probabilities (R, C+1)."""
    nll = -torch.log(probs.clamp_min(1e-6)).gather(1, target[:, None])[:, 0]
    return (nll * weights).mean()


def positive_pixels(masks: torch.Tensor, has_mask: torch.Tensor, train_t: torch.Tensor):
    """(frame, pixel) indices of the training pixels inside label boxes (mask class > 0)."""
    sel = train_t[has_mask[train_t]]
    fr, px = (masks[sel] > 0).nonzero(as_tuple=True)
    return sel[fr], px


def _extra(bounds, sizing, curve, gen) -> dict:
    return {"bounds": bounds.to_json() if bounds else None, "sizing": asdict(sizing) if sizing else None,
            "curve": curve, "rng": gen.get_state()}


def evaluate_frames(model: StaticModel, data: FlightData, indices: list[int], min_box_px: float = 6.0,
                    out_dir: Path | None = None, rules: BoxRules | None = None,
                    keep_probs: bool = False) -> dict:
    """PSNR / SSIM of rendered frames against the recorded images (mean appearance, as for a novel
    view), and box IoU of mask blobs against the frames' label boxes (boxes >= ``min_box_px`` on
    their shorter side); blobs -> boxes by the synthesis rules (``boxes_from_probabilities`` with
    ``rules``, default ``BoxRules()``). Optionally writes side-by-side PNGs; with ``keep_probs``
    the summary also holds ``"mask_probs"``: frame index -> rendered (H, W, K) float16 mask, to
    re-score other box rules without rendering."""
    import cv2

    rows, ious, probs = [], [], {}
    for i in indices:
        r = model.render_image(data.camera, data.cam_from_world[i])
        gt = data.images[i].numpy()
        row = {"frame": data.names[i], "psnr": psnr(r["rgb"], gt), "ssim": ssim(r["rgb"], gt)}
        if keep_probs and "mask_probs" in r:
            probs[i] = np.asarray(r["mask_probs"], dtype=np.float16)
        if bool(data.has_mask[i]):
            truth = [b for b in label_boxes(data.boxes[i]) if min(b.width, b.height) >= min_box_px]
            found = match_boxes(truth, boxes_from_probabilities(r["mask_probs"], rules))
            ious += found
            row["box_iou"] = float(np.mean(found)) if found else None
        rows.append(row)
        if out_dir:
            out_dir.mkdir(parents=True, exist_ok=True)
            both = np.concatenate([(np.clip(r["rgb"], 0, 1) * 255).astype(np.uint8), gt], axis=1)
            cv2.imwrite(str(out_dir / f"{Path(data.names[i]).stem}_render_vs_truth.png"),
                        cv2.cvtColor(both, cv2.COLOR_RGB2BGR))
    summary = {"frames": rows, "psnr": float(np.mean([r["psnr"] for r in rows])) if rows else None,
               "ssim": float(np.mean([r["ssim"] for r in rows])) if rows else None,
               "box_iou_mean": float(np.mean(ious)) if ious else None,
               "box_iou_ge_0.5": float(np.mean(np.asarray(ious) >= 0.5)) if ious else None,
               "boxes_evaluated": len(ious)}
    if keep_probs:
        summary["mask_probs"] = probs
    return summary


def evaluate_heldout(model: StaticModel, data: FlightData, indices: list[int],
                     out_dir: Path | None = None) -> dict | None:
    """``evaluate_frames`` on the held-out frames plus the mask threshold calibrated there
    (``"mask_threshold"``, :func:`fields.mask_calibration.calibrate_threshold`; None without label
    boxes >= 6 px): what ``uavsim fit`` writes to ``fit.json`` and ``uavsim synth`` reads. None
    without held-out frames."""
    from fields.mask_calibration import calibrate_threshold

    if not indices:
        return None
    summary = evaluate_frames(model, data, indices, out_dir=out_dir, keep_probs=True)
    probs = summary.pop("mask_probs")
    truth = {i: label_boxes(data.boxes[i]) for i in probs if bool(data.has_mask[i])}
    summary["mask_threshold"] = calibrate_threshold({i: probs[i] for i in truth}, truth)
    return summary


def write_fit_json(path: Path, result: FitResult, cfg: FitConfig, heldout: dict | None) -> None:
    model = result.model
    n = model.param_count()
    payload = {"kind": "static", "encoding": model.field_config.encoding, "sampler": model.sampler_config.kind,
               "steps": result.step,
               "train_s": round(result.train_s, 2), "params": n, "mb": round(n * 4 / 1e6, 2),
               "sizing": asdict(result.sizing) if result.sizing else None,
               "bounds": result.bounds.to_json() if result.bounds else None,
               "heldout": heldout, "curve": result.curve, "config": asdict(cfg)}
    if result.resume_kept:  # the options asked for another model than the resumed checkpoint holds
        payload["resume_kept_model"] = {k: [old, new] for k, (old, new) in result.resume_kept.items()}
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(payload, indent=1, default=float) + "\n")
    os.replace(tmp, path)
