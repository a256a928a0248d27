"""Fitting a dynamic model (stock or extended K-Planes) to a timed flight; checkpoint and evaluation.

Both kinds train with the same options (:class:`DynamicFitConfig`) and stop on the same iteration
count or wall-clock budget. Rays are drawn uniformly over (training frame, pixel), except a share
``box_ray_fraction`` drawn from pixels inside label boxes, with every per-ray loss importance-weighted
so the objective stays the uniform one; each ray carries its frame's normalised time and whether
its pixel lies inside a labelled person box ("dynamic").

Losses (both kinds): MSE on RGB; ``lambda_dist`` x distortion; ``lambda_empty`` x density in the air
(from 10 % of training on; by default on telemetry poses only); ``lambda_mask`` x the class-mask NLL
(filled boxes, as the static fit, for synthesis); K-Planes regularisers ``lambda_tv`` x spatial plane
total variation, ``lambda_time_smooth`` x second difference along t, ``lambda_time_l1`` x L1 of the
time planes towards 1. Extended only: ``lambda_dynamic`` x BCE of the rendered time-plane mask channel against
the box mask, ``lambda_cos`` x ``L_cos`` between static and dynamic spatial plane features at the
samples, and mask-gated gradients (static pixels update static planes only, dynamic pixels dynamic
planes only; :func:`fields.kplanes.gate_grad`).
"""

from __future__ import annotations

import json
import logging
import math
import os
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from fields.description_diff import description_differences
from fields.dynamic_data import DynamicFlightData
from fields.dynamic_model import DynamicModel, make_field_config, plane_sizing
from fields.evaluation import label_boxes, match_boxes, psnr, ssim
from fields.kplanes import coarse_to_fine_weights, cosine_separation
from fields.mask_boxes import boxes_from_probabilities
from fields.model import SamplerConfig
from fields.pose_drift import knot_count, warmup_scale
from fields.scene import SceneBounds, scene_bounds
from fields.synthesis import match_boxes as match_detections
from fields.training import (
    configure_threads,
    device,
    importance_weights,
    positive_pixels,
    schedule_progress,
    upper_box_points,
)

log = logging.getLogger(__name__)

CHECKPOINT = "dynamic.pt"
FORMAT = "uavsim-dynamic-1"


@dataclass
class DynamicFitConfig:
    """Training options shared by both kinds (the comparison changes ``kind`` only)."""

    kind: str = "kplanes-ext"
    n_samples: int = 32
    iters: int = 20000
    #: wall-clock training budget, s (None: iterations only)
    budget_s: float | None = 300.0
    batch_rays: int = 1024
    lr: float = 1e-2
    lr_final: float = 0.1
    #: hold out every k-th frame in time order (2 = every other frame, the paper's split; <= 1: none)
    holdout_every: int = 2
    seed: int = 0
    threads: int | None = None
    features: int = 16
    hidden: int = 64
    appearance_dim: int = 8
    #: cap on the finest plane resolution per side (the data's GSD sets it below the cap). On the bench flights the
    #: cap binds (18 cm cells against 12.6 cm GSD); 384 lets the GSD decide, at 1.8-1.9x the MB, and measured no
    #: better at 900 s (-0.13 / +0.02 dB extended / stock, 80 frames; bench/RESULTS.md, Table III session 18)
    max_resolution: int = 256
    cell_factor: float = 1.0
    #: the fresh field's optical depth along a vertical ray through the whole box (sets the density
    #: bias, :func:`fields.dynamic_model.density_bias_for`); None: the field's fixed bias of -1, an optical
    #: depth of ~4 through the bench flights' 10-11 m boxes. In that fog 99 % of background rays ended in the
    #: air for the first 13-17 % of a 900 s fit; stock never came down (85 % at the end). At 0.2 against
    #: the fog, 900 s, one seed per row: stock +2.9 / +1.7-1.9 dB held-out on the 80 / 300-frame telemetry
    #: flights and +5-6 dB from 30 m; extended -1.0 / -0.6-0.9 dB held-out, +0.7 dB from 30 m (80 frames),
    #: +0.8 dB held-out on exact poses, where it also did without the pose correction what the correction
    #: had done (30.61 dB against 30.65 with it in the fog, 27.84 without) (bench/RESULTS.md, Table III
    #: session 32)
    init_optical_depth: float | None = 0.2
    lambda_dist: float = 2e-3
    lambda_mask: float = 0.05
    mask_fg_weight: float = 4.0
    #: background probability of the fresh class-mask head (None: torch's default, ~uniform, i.e.
    #: 75 % "person" wherever no mask ray has been yet)
    mask_init_background: float | None = 0.99
    #: what the class-mask head reads: "geometry" or "planes" (its own small K-Planes; see
    #: :class:`fields.kplanes.KPlanesFieldConfig`)
    mask_encoding: str = "planes"
    #: share of each ray batch drawn from pixels inside label boxes (people are ~2 % of a frame).
    #: Every per-ray loss (colour, class mask, time-plane mask) is importance-weighted, so the
    #: objective is the uniform one with less variance on the people; for extended K-Planes, whose
    #: dynamic planes learn from box pixels only, that is ~12x more rays for them at 0.25. (An
    #: unweighted colour loss cost 2.5 dB held-out at 600 steps: bench/RESULTS.md, session 4.)
    box_ray_fraction: float = 0.25
    lambda_tv: float = 2e-4
    lambda_time_smooth: float = 1e-3
    lambda_time_l1: float = 1e-4
    lambda_dynamic: float = 0.05
    #: weight of L_cos (1e-2 slowed learning: 18.1 vs 19.7 dB train PSNR after 150 steps, 256 rays)
    lambda_cos: float = 1e-4
    #: ``L_cos`` is estimated on the batch's first this-many samples (whole random rays)
    cos_points: int = 4096
    #: ``lambda_empty`` x the mean density (clamped at 10) at ``empty_points`` random points and times
    #: in the box above ``empty_above`` of its height: a prior that air is empty unless the images say
    #: otherwise, against the layer in the air that a straight pass cannot rule out (stock K-Planes
    #: paints the scene there; extended falls onto it on some seeds of the 300-frame flight). From
    #: step 0 it was a trade between the bench flights (Table III sessions 20, 21); started at
    #: ``empty_from`` 0.1 it cost neither telemetry flight anything on two seeds and cured the seed that
    #: took the layer (26.85 -> 28.00 dB held-out, 22.02 -> 24.93 from 30 m; Table III session 23).
    #: Whether it acts: ``air_prior``. 0: off
    lambda_empty: float = 1e-3
    #: the air prior acts (True), does not (False), or None: on when the poses are telemetry, off when
    #: every pose is SfM-refined. On SfM poses extended found the ground without it, and it cost 0.53 /
    #: 1.46 dB held-out (300 frames, seeds 0 / 1, 900 s; bench/RESULTS.md, Table III sessions 23, 24)
    air_prior: bool | None = None
    empty_points: int = 2048
    empty_above: float = 0.3
    #: the prior applies while this share of training (of the budget or the steps) has not passed,
    #: then stops (1: throughout). With the prior from step 0, stopping at 0.3 changed nothing on either
    #: flight (Table III session 21)
    empty_until: float = 1.0
    #: the prior starts once this share of training (of the budget or the steps) has passed. From
    #: step 0 it cost extended 0.6 dB held-out on the 80-frame flight even when it stopped after ~130
    #: steps (Table III session 22). At 0.1 (900 s, ~250 steps), extended's held-out PSNR against the
    #: prior off over two seeds: 80 frames +0.11 / -0.03 dB, 300 frames +0.18 / +1.15 dB (the second a
    #: fit that took the layer without the prior); from 30 m -0.44 / -0.05 and +0.98 / +2.91 dB (Table
    #: III sessions 22, 23). Stock has settled on its layer by then and keeps it; from step 0 the prior
    #: takes stock off most of it (depth error 64 -> 6-9 %, Table III session 23)
    empty_from: float = 0.1
    #: extended only: gate gradients by the box mask (the paper's choice; False for an ablation). Off, extended
    #: gained 0.8-1.25 dB held-out and lost 1.1-1.3 dB in views from 30 m (80-frame telemetry flight, two seeds;
    #: bench/RESULTS.md, Table III session 33): the gate is what keeps the background consistent from higher up
    gate: bool = True
    #: extended with ``gate`` only: order each batch's rays into the runs that the gated encoding samples in
    #: place (:func:`gate_run_order`); each ray keeps the jitter it was drawn with, so a step computes what
    #: the drawn order would, up to float summation order. 7-11 % more steps fit in a budget; held-out PSNR
    #: at 900 s is within the fit's run-to-run spread (~0.8 dB at one seed; bench/RESULTS.md, Table III
    #: sessions 26 and 27)
    gate_ray_runs: bool = True
    #: extended only: the dynamic time planes act on ``f_d`` in proportion to the point's dynamic
    #: probability (:class:`fields.kplanes.KPlanesConfig` ``time_gate``). None: on when every frame's
    #: pose is SfM-refined, off on telemetry poses. On SfM poses it was worth +1.23 / +2.06 dB held-out
    #: (two seeds, 300 frames, all in the background) and -0.25 / +0.29 dB on 80 frames; on telemetry poses
    #: +0.32 / +0.20 dB on 80 frames but -4.29 dB on the 300-frame flight, whose poses drift 0.4 m (with
    #: the pose-drift knots; without them +0.32 dB)
    #: (bench/RESULTS.md, Table III session 11)
    time_gate: bool | None = None
    #: extended only: the dynamic planes cover the layer from the ground up to this height, metres (people
    #: stand up to ~1.9 m); above it the field is static (:class:`fields.kplanes.KPlanesConfig`
    #: ``dynamic_z_top``). None: the whole box. On the 300-frame SfM flight (a 16.6 m box, the layer its lowest
    #: 3.3 m): 14 % fewer parameters, 15-16 % more steps in a budget, and held-out PSNR at 900 s 31.41 / 31.47
    #: dB against 29.30 / 30.71 for the whole box (seeds 2 / 3, same day; bench/RESULTS.md, Table III session 28)
    dynamic_height_m: float | None = 2.5
    #: learn a time-smooth correction of the telemetry poses (:mod:`fields.pose_drift`) with one
    #: knot per this many seconds of flight (None: take the poses as given). Worth +0.85 / +2.44 dB
    #: held-out to extended K-Planes on the 80 / 300-frame bench flights, +0.18 / +0.05 dB to stock
    #: (bench/RESULTS.md, Table III session 7); 1 s beat 0.5 s (-0.33 dB) and 3 s (-3.05 dB) for
    #: extended on the 300-frame flight. Not learned on SfM-refined poses (``pose_drift_on_sfm``)
    pose_knot_s: float | None = 1.0
    #: coarser knot levels on top of the ``pose_knot_s`` ones, one spacing (s) per level, their
    #: corrections summed (:class:`fields.pose_drift.PoseDrift`): the slow drift pools more rays per knot.
    #: Alone they widened extended's two outcomes on the 300-frame telemetry flight (seeds 0 / 1: 20.86 /
    #: 28.15 dB held-out); with ``pose_delay`` 0.1 both seeds gave 27.42 / 27.22 (25.64-27.44 before), and
    #: 28.09 on 80 frames (27.99) (bench/RESULTS.md, Table III session 17)
    pose_knot_coarse_s: tuple[float, ...] = (4.0, 15.0)
    #: the pose knots stay still for this share of training, then their step sizes ramp up linearly
    #: over as long again (:func:`fields.pose_drift.warmup_scale`); 0: they learn from the first step,
    #: and on a random field they walk decimetres before there is a world to line the frames up to
    pose_delay: float = 0.1
    #: on top of the knots, one correction per training frame (:class:`fields.pose_drift.PoseDrift`
    #: ``frame_t01``), of what the knots cannot represent: the white per-frame jitter of telemetry poses
    #: that knots a second apart cannot follow. Held-out frames get the knots alone. Same step sizes,
    #: delay and penalty weight as the knots. Off: the rows line the training frames up (extended, 80 frames:
    #: 1.00 -> 0.80 px) but held-out PSNR did not move (-0.05 dB on 80 frames, +0.07 on 300; one seed, 900 s;
    #: bench/RESULTS.md, Table III session 19)
    pose_per_frame: bool = False
    #: learn the correction even when every frame's pose was refined by SfM (``poses.json`` source
    #: "sfm"); off: such poses are taken as given. On SfM poses the knots cost held-out PSNR on both
    #: bench flights, both kinds: 80 frames stock 0.05 / extended 1.13 dB, 300 frames 0.84 / 0.70 dB
    #: (bench/RESULTS.md, Table III sessions 8 and 9)
    pose_drift_on_sfm: bool = False
    #: Adam step sizes of the pose knots (decayed with the field's schedule): metres, radians
    pose_lr_m: float = 5e-3
    pose_lr_rad: float = 5e-5
    #: weight of the knots' mean squared correction (m^2; anchors the gauge to the telemetry)
    lambda_pose: float = 1e-4
    #: the pose knots learn from rays outside the label boxes only (a walking person's motion looks
    #: like a pose error; box rays still render through the corrected pose, without moving it). Held-out
    #: dB on the 300-frame telemetry flight: extended + time gate 20.99 -> 23.53, extended 25.28 -> 24.70,
    #: stock 26.24 -> 26.40; on 80 frames extended 27.41 -> 27.67, stock 25.51 -> 25.40. Off: it leaves
    #: extended below stock on the long flight (bench/RESULTS.md, Table III session 13)
    pose_from_background: bool = False
    #: coarse-to-fine: the finer plane scales fade in over this share of training (BARF's schedule,
    #: :func:`fields.kplanes.coarse_to_fine_weights`), both kinds alike; 0: every scale at full weight. At 0.3,
    #: extended on the 300-frame telemetry flight, 900 s: seed 0 23.68 dB (27.44 without), seed 1 27.20 (25.64):
    #: it moves which seed's pose knots fail to line the frames up, no cure (bench/RESULTS.md, Table III session 16)
    coarse_to_fine: float = 0.0
    checkpoint_every_s: float = 60.0
    log_every_s: float = 10.0


@dataclass
class DynamicFitResult:
    model: DynamicModel
    step: int
    train_s: float
    curve: list[dict] = field(default_factory=list)
    bounds: SceneBounds | None = None
    sizing: dict | None = None
    #: the running depth shortfall of the background rays against the ground plane at the end
    #: (the median of :func:`ray_shortfall`; None: no such ray), and the steps the air prior acted in
    ground_shortfall: float | None = None
    #: the running share of background rays ending in the air (:func:`shortfall_stats`) at the end
    air_share: float | None = None
    air_prior_steps: int = 0
    #: the options this run trained with: those asked for, except that a resumed fit keeps its checkpoint's
    #: model options (:func:`options_the_checkpoint_overrides`). None: not from :func:`fit_dynamic`
    config: DynamicFitConfig | None = None


def split(dd: DynamicFlightData, every: int) -> tuple[list[int], list[int]]:
    """Training and held-out frame indices: in time order, position ``k`` is held out when
    ``k % every == every - 1`` (every = 2: every other frame)."""
    order = [int(i) for i in np.argsort(dd.times_us, kind="stable")]
    if every <= 1 or len(order) == 1:
        return sorted(order), []
    test = sorted(order[k] for k in range(len(order)) if k % every == every - 1)
    train = sorted(order[k] for k in range(len(order)) if k % every != every - 1)
    return train, test


#: the options that shape the model :func:`build_model` makes; a resumed fit keeps its checkpoint's model,
#: so these take effect only in a fresh fit (:func:`options_the_checkpoint_overrides`). A different ``kind``
#: is an error instead. Kept by hand: a test changes every option in turn and checks which ones change the
#: built model's description
MODEL_OPTIONS = ("n_samples", "features", "hidden", "appearance_dim", "max_resolution", "cell_factor",
                 "init_optical_depth", "mask_init_background", "mask_encoding", "time_gate", "dynamic_height_m",
                 "pose_knot_s", "pose_knot_coarse_s", "pose_per_frame", "pose_drift_on_sfm")


def options_the_checkpoint_overrides(saved: dict, cfg: DynamicFitConfig) -> dict[str, tuple]:
    """``{name: (saved value, asked value)}`` for each of :data:`MODEL_OPTIONS` whose value in the
    checkpoint's ``fit_config`` (``saved``) differs from ``cfg``'s: the resumed model keeps the saved one.
    Options a checkpoint predates are not listed (their saved value is unknown). Compared as model
    descriptions are (:func:`fields.description_diff.description_differences`: a saved list equals the
    same tuple); a saved list comes back as the tuple the option holds."""
    asked = asdict(cfg)
    known = [name for name in MODEL_OPTIONS if name in saved]
    diff = description_differences({n: saved[n] for n in known}, {n: asked[n] for n in known})
    return {name: (tuple(old) if isinstance(old, list) else old, new) for name, (old, new) in diff.items()}


def build_model(dd: DynamicFlightData, train_idx: list[int], cfg: DynamicFitConfig, flight: Path | None):
    data = dd.data
    bounds = scene_bounds(flight, data.camera, [data.cam_from_world[i] for i in train_idx])
    sizing = plane_sizing(bounds.extent, bounds.finest_gsd_m, cfg.max_resolution, cfg.cell_factor)
    gate, why_gate = time_gate(dd, cfg)
    z_top, why_layer = dynamic_layer_top(bounds, cfg.dynamic_height_m)
    fc = make_field_config(cfg.kind, bounds, sizing, dd.n, data.n, len(data.classes), cfg.features, cfg.hidden,
                           cfg.appearance_dim, cfg.mask_init_background, cfg.mask_encoding, gate, z_top,
                           cfg.init_optical_depth)
    ext = np.asarray(bounds.extent)
    radius = 0.5 * float(np.hypot(ext[0], ext[1]))
    knots, coarse, why = pose_knots(dd, cfg)
    sizing.reasoning.append(why)
    if cfg.kind == "kplanes-ext":
        sizing.reasoning += [why_gate, why_layer]
    sizing.reasoning.append(air_prior(dd, cfg)[1])
    if cfg.init_optical_depth is not None:
        sizing.reasoning.append(f"fresh field: optical depth {cfg.init_optical_depth:g} through the box's "
                                f"{bounds.hi[2] - bounds.lo[2]:.1f} m height (density bias {fc.density_bias:.2f})")
    frame_t01 = dd.t01()[train_idx].tolist() if knots and cfg.pose_per_frame else []  # rows: training frames
    model = DynamicModel(cfg.kind, fc, SamplerConfig("stratified", cfg.n_samples), bounds.ground_z, radius,
                         dd.t0_us, dd.span_us, pose_knots=knots, pose_coarse_knots=coarse, pose_frame_t01=frame_t01)
    return model, bounds, asdict(sizing)


def dynamic_layer_top(bounds: SceneBounds, height_m: float | None) -> tuple[float, str]:
    """The normalised box height (0, 1] up to which the dynamic planes reach: ``height_m`` above the
    ground (``bounds.ground_z``, world ENU z up), and why. None, or a layer reaching the box top: 1."""
    lo_z, hi_z = float(bounds.lo[2]), float(bounds.hi[2])
    if height_m is None:
        return 1.0, "dynamic planes: the whole box height"
    if not (math.isfinite(height_m) and height_m > 0):
        raise ValueError(f"dynamic_height_m must be a positive number of metres, got {height_m}")
    top = (bounds.ground_z + height_m - lo_z) / (hi_z - lo_z)
    if top >= 1.0:
        return 1.0, f"dynamic planes: the whole box height ({hi_z - lo_z:.2f} m <= ground + {height_m:g} m)"
    top = max(top, 1e-3)
    return top, (f"dynamic planes: the lowest {top * (hi_z - lo_z):.2f} m of the {hi_z - lo_z:.2f} m box (ground + "
                 f"{height_m:g} m), the layer people walk in; static above")


def time_gate(dd: DynamicFlightData, cfg: DynamicFitConfig) -> tuple[bool, str]:
    """Whether extended K-Planes gates its time planes by the dynamic mask here, and why (for fit.json)."""
    if cfg.time_gate is not None:
        return bool(cfg.time_gate), f"time gate: {'on' if cfg.time_gate else 'off'} (set explicitly)"
    if dd.all_poses_sfm:
        return True, f"time gate: on, all {dd.n} poses are SfM-refined"
    return False, "time gate: off, the poses are telemetry (the gate was measured to fail on drifting poses)"


def air_prior(dd: DynamicFlightData, cfg: DynamicFitConfig) -> tuple[bool, str]:
    """Whether the air prior (``lambda_empty``) acts in this fit, and why (a line for fit.json)."""
    if cfg.lambda_empty <= 0:
        return False, "air prior: off (lambda_empty 0)"
    if cfg.air_prior is not None:
        return bool(cfg.air_prior), f"air prior: {'on' if cfg.air_prior else 'off'} (set explicitly)"
    if dd.all_poses_sfm:
        return False, (f"air prior: off, all {dd.n} poses are SfM-refined (there it was measured to cost "
                       "held-out PSNR; --air-prior on forces it)")
    return True, (f"air prior: on from {cfg.empty_from:.0%} of training, the poses are telemetry (against a "
                  "layer in the air that a straight pass cannot rule out)")


def pose_knots(dd: DynamicFlightData, cfg: DynamicFitConfig) -> tuple[int, list[int], str]:
    """Knots of the learned pose-drift correction for this flight (finest level, then the coarser
    levels), and why (a line for fit.json)."""
    if not cfg.pose_knot_s:
        return 0, [], "pose drift: not learned (pose_knot_s off)"
    if dd.all_poses_sfm and not cfg.pose_drift_on_sfm:
        return 0, [], (f"pose drift: not learned, all {dd.n} poses are SfM-refined (an explicit --pose-knot-s or "
                       "pose_drift_on_sfm learns it)")
    span_s = dd.span_us / 1e6
    knots = knot_count(span_s, cfg.pose_knot_s)
    coarse = [knot_count(span_s, s) for s in cfg.pose_knot_coarse_s]
    why = f"pose drift: {knots} knots, one per {cfg.pose_knot_s:g} s of flight"
    if coarse:
        why += ", plus coarser levels of " + ", ".join(
            f"{k} knots ({s:g} s)" for k, s in zip(coarse, cfg.pose_knot_coarse_s, strict=True))
    if cfg.pose_per_frame:
        why += "; one correction per training frame on top"
    if cfg.pose_delay > 0:
        why += f"; still for the first {cfg.pose_delay:.0%} of training, full step size from {2 * cfg.pose_delay:.0%}"
    return knots, coarse, why


def _optimizer(model: DynamicModel, cfg: DynamicFitConfig):
    """Adam; the pose knots (if any) in their own groups, each group's ``base_lr`` decayed alike."""
    drift = model.pose_drift
    pose_ids = {id(p) for p in drift.parameters()} if drift is not None else set()
    groups = [{"params": [p for p in model.parameters() if id(p) not in pose_ids], "base_lr": cfg.lr}]
    if drift is not None:
        groups += [{"params": drift.translation_params(), "base_lr": cfg.pose_lr_m, "pose": True},
                   {"params": drift.rotation_params(), "base_lr": cfg.pose_lr_rad, "pose": True}]
    for g in groups:
        g["lr"] = g["base_lr"]
    return torch.optim.Adam(groups, betas=(0.9, 0.99), eps=1e-15)


def save_checkpoint(path: Path, model: DynamicModel, optim, step: int, train_s: float, cfg: DynamicFitConfig,
                    extra: dict) -> None:
    """Atomic write (temp + rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"format": FORMAT, "model": model.describe(), "state": model.state_dict(),
                "optim": optim.state_dict() if optim else None, "step": step, "train_s": train_s,
                "fit_config": asdict(cfg), **extra}, tmp)
    os.replace(tmp, path)


def load_dynamic_checkpoint(path: str | Path, map_location=None) -> tuple[DynamicModel, dict]:
    """The model (eval mode) and the raw checkpoint dict."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no fitted dynamic field (run 'uavsim fit --kind kplanes-ext' first)")
    ck = torch.load(path, map_location=map_location or device(), weights_only=False)
    if ck.get("format") != FORMAT:
        raise ValueError(f"{path}: not a uavsim dynamic field checkpoint")
    model = DynamicModel.from_description(ck["model"])
    model.load_state_dict(ck["state"])
    return model.to(map_location or device()).eval(), ck


def air_density(field, n: int, above: float, generator: torch.Generator) -> torch.Tensor:
    """Density (1/m, clamped at 10) of ``field`` (:class:`fields.kplanes.KPlanesField`) at ``n`` points
    uniform in its box above the share ``above`` of its height (world ENU), at uniform times in [0, 1]."""
    points = upper_box_points(field.lo, field.hi, n, above, generator)
    times = torch.rand(n, device=points.device, generator=generator)
    return field.density(points, times).clamp_max(10.0)


#: a background ray "ends in the air" when it ends more than this share short of the ground plane:
#: from 15 m up, 6 m above the ground (structures reach 4.5 m, single trees 9 m)
AIR_MARGIN = 0.4


@torch.no_grad()
def ray_shortfall(depth: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor, ground_z: float,
                  keep: torch.Tensor) -> torch.Tensor:
    """How far short of the ground each ray in ``keep`` ends: ``1 - depth / t_ground`` (K,) over those rays
    that look down from above the plane, with ``t_ground`` the distance (m) along the unit ray from its
    origin (world ENU) to the plane ``z = ground_z``. 0: on the ground plane; 0.65: a third of the way
    down, on a layer in the air; negative: beyond the plane. ``depth`` (R,) or (R, 1) m, expected depth;
    ``keep`` (R,) bool, e.g. the pixels outside every person's box. Empty when no kept ray qualifies
    (looking up or level, starting below the plane, depth not finite)."""
    t_ground = (origins[:, 2] - ground_z) / (-dirs[:, 2]).clamp_min(1e-6)
    ok = keep & (dirs[:, 2] < -1e-3) & (origins[:, 2] > ground_z) & torch.isfinite(depth.reshape(-1))
    return 1.0 - depth.reshape(-1)[ok].detach() / t_ground[ok]


def shortfall_stats(shortfall: torch.Tensor) -> tuple[float, float] | None:
    """The median of :func:`ray_shortfall`'s values (trees and buildings make single rays short, not the
    median) and the share of rays ending in the air (more than :data:`AIR_MARGIN` short: a layer over
    part of the flight would raise it without moving the median). None for no ray."""
    if shortfall.numel() == 0:
        return None
    return float(shortfall.median()), float((shortfall > AIR_MARGIN).float().mean())


def running_average(previous: float | None, value: float) -> float:
    """The exponential average over training steps that the loop logs (weight 0.05 on the newest)."""
    return value if previous is None else 0.95 * previous + 0.05 * value


def regularisers(enc, cfg: DynamicFitConfig) -> torch.Tensor:
    """The K-Planes regularisers of encoding ``enc`` (:class:`fields.kplanes.KPlanesEncoding`) weighted by ``cfg``."""
    return (cfg.lambda_tv * enc.total_variation() + cfg.lambda_time_smooth * enc.time_smoothness()
            + cfg.lambda_time_l1 * enc.time_l1())


def fit_dynamic(dd: DynamicFlightData, cfg: DynamicFitConfig, out_dir: Path | None = None,
                flight: Path | None = None, resume: bool = False) -> DynamicFitResult:
    """Train a dynamic model; checkpoints go to ``out_dir/dynamic.pt``."""
    configure_threads(cfg.threads)
    dev = device()
    torch.manual_seed(cfg.seed)
    gen = torch.Generator(device=dev).manual_seed(cfg.seed)
    train_idx, _ = split(dd, cfg.holdout_every)
    data = dd.data
    ckpt = out_dir / CHECKPOINT if out_dir else None
    if resume and ckpt and ckpt.is_file():
        model, ck = load_dynamic_checkpoint(ckpt, dev)
        if model.kind != cfg.kind:
            raise ValueError(f"{ckpt} holds a {model.kind} field, not {cfg.kind}; drop --resume to start over")
        kept = options_the_checkpoint_overrides(ck.get("fit_config", {}), cfg)
        if kept:
            log.warning("resuming %s: the model keeps the checkpoint's shape, so these options apply only to a "
                        "fresh fit (drop --resume to start over): %s", ckpt,
                        "; ".join(f"{k}: {old!r} -> {new!r}" for k, (old, new) in kept.items()))
            # the run's record (checkpoint, fit.json) states the model it trained, not the options asked for
            cfg = replace(cfg, **{k: old for k, (old, _) in kept.items()})
        optim = _optimizer(model, cfg)
        if ck.get("optim"):
            built = [{k: v for k, v in g.items() if k != "params"} for g in optim.param_groups]
            optim.load_state_dict(ck["optim"])  # takes the saved groups' keys, dropping the ones just built
            for g, b in zip(optim.param_groups, built, strict=True):  # keys older checkpoints lack
                g.setdefault("base_lr", cfg.lr)  # from before per-group step sizes
                g.setdefault("pose", b.get("pose", False))  # from before the pose delay
        step, train_s, curve = int(ck["step"]), float(ck["train_s"]), list(ck.get("curve", []))
        bounds = SceneBounds(**ck["bounds"]) if ck.get("bounds") else None
        sizing = ck.get("sizing")
        if "rng" in ck:
            gen.set_state(ck["rng"])
    else:
        model, bounds, sizing = build_model(dd, train_idx, cfg, flight)
        model = model.to(dev)
        optim = _optimizer(model, cfg)
        step, train_s, curve = 0, 0.0, []
    model.train()
    log.info("model: %s, %d parameters (%.1f MB), planes %s x %s, T=%d", model.kind, model.param_count(),
             model.param_count() * 4 / 1e6, model.field_config.planes.base_resolution,
             model.field_config.planes.multipliers, model.field_config.planes.time_resolution)

    from fields.data import RayBank

    bank = RayBank(data.camera, data.cam_from_world, dev)
    images = data.images.to(dev).view(data.n, -1, 3)
    masks = data.masks.to(dev).view(data.n, -1).long()
    has_mask = data.has_mask.to(dev)
    t01 = torch.from_numpy(dd.t01()).to(dev)
    train_t = torch.tensor(train_idx, device=dev)
    hw = bank.hw
    fg_w = torch.ones(len(data.classes) + 1, device=dev)
    fg_w[1:] = cfg.mask_fg_weight
    ext = model.extended
    pos_frame, pos_pixel = positive_pixels(masks, has_mask, train_t)
    n_box = int(round(cfg.box_ray_fraction * cfg.batch_rays)) if len(pos_frame) else 0
    iw = importance_weights(cfg.batch_rays, n_box, len(train_idx) * hw, len(pos_frame), dev)

    enc = model.field.encoding
    drift = model.pose_drift
    row_of = None  # flight frame index -> the pose correction's per-frame row (training frames only)
    if drift is not None and drift.frames:
        if drift.frames != len(train_idx):
            raise ValueError(f"the pose correction has {drift.frames} per-frame rows but the flight has "
                             f"{len(train_idx)} training frames; drop --resume to start over")
        row_of = torch.full((data.n,), -1, dtype=torch.long, device=dev)
        row_of[train_t] = torch.arange(len(train_idx), device=dev)

    last_log = last_ckpt = 0.0
    interactive = sys.stderr.isatty()
    t_mark = time.perf_counter()
    loss_ema = None
    # running ground shortfall of the background rays (:func:`shortfall_stats`) and the steps the air
    # prior acted in, carried over a resume through the curve
    shortfall_ema = curve[-1].get("ground_shortfall") if curve else None
    air_ema = curve[-1].get("air_share") if curve else None
    prior_steps = int(curve[-1].get("air_prior_steps", 0)) if curve else 0
    ground_z = model.background.ground_z
    prior_on, why_prior = air_prior(dd, cfg)
    log.info("%s", why_prior)
    # rays in the runs the gated encoding samples in place (:func:`gate_run_order`); L_cos reads the first
    # ``cos_points`` samples, i.e. the leading whole rays
    gate_runs = ext and cfg.gate and cfg.gate_ray_runs
    cos_rays = math.ceil(cfg.cos_points / model.sampler.n_samples) if gate_runs and cfg.lambda_cos > 0 else 0
    while step < cfg.iters and (cfg.budget_s is None or train_s < cfg.budget_s):
        share = schedule_progress(step, cfg.iters, train_s, cfg.budget_s)  # of training, 0..1
        decay = cfg.lr_final ** share
        lr = cfg.lr * decay
        pose_scale = warmup_scale(share, cfg.pose_delay)
        for g in optim.param_groups:
            g["lr"] = g["base_lr"] * decay * (pose_scale if g.get("pose") else 1.0)
        if cfg.coarse_to_fine > 0:
            enc.set_scale_weights(coarse_to_fine_weights(enc.n_scales, share, cfg.coarse_to_fine))
        fi = train_t[torch.randint(len(train_idx), (cfg.batch_rays - n_box,), device=dev, generator=gen)]
        pi = torch.randint(hw, (cfg.batch_rays - n_box,), device=dev, generator=gen)
        if n_box:
            k = torch.randint(len(pos_frame), (n_box,), device=dev, generator=gen)
            fi, pi = torch.cat([fi, pos_frame[k]]), torch.cat([pi, pos_pixel[k]])
        order = None
        if gate_runs:
            order = gate_run_order(masks[fi, pi] > 0, cos_rays)
            fi, pi = fi[order], pi[order]
        o, d = bank.rays(fi, pi)
        cls = masks[fi, pi]
        if drift is not None:
            o, d = drift.apply(o, d, t01[fi], None if row_of is None else row_of[fi])
            if cfg.pose_from_background:
                o, d = background_pose_grad(o, d, cls == 0)
        target = images[fi, pi].float() / 255.0
        dyn = (cls > 0).float()
        mask_w = iw[(cls > 0).long()]  # importance weights of the per-ray losses (all 1 without box rays)
        gate = dyn if (ext and cfg.gate) else None
        res = model.render_rays(o, d, t01[fi], fi, train=True, with_mask=cfg.lambda_mask > 0, dynamic_gate=gate,
                                with_features=ext and cfg.lambda_cos > 0, feature_points=cfg.cos_points, generator=gen,
                                jitter_rows=order)
        loss_rgb = torch.mean(((res["rgb"] - target) ** 2).mean(-1) * mask_w)
        loss = loss_rgb + regularisers(model.field.encoding, cfg)
        if model.pose_drift is not None and cfg.lambda_pose > 0:
            loss = loss + cfg.lambda_pose * model.pose_drift.penalty()
        if cfg.lambda_dist > 0:
            loss = loss + cfg.lambda_dist * model.distortion(res)
        stats = shortfall_stats(ray_shortfall(res["depth"], o, d, ground_z, cls == 0))
        if stats is not None:
            shortfall_ema, air_ema = running_average(shortfall_ema, stats[0]), running_average(air_ema, stats[1])
        if prior_on and cfg.empty_from <= share < cfg.empty_until:
            loss = loss + cfg.lambda_empty * air_density(model.field, cfg.empty_points, cfg.empty_above, gen).mean()
            prior_steps += 1
        m_ok = has_mask[fi]
        if cfg.lambda_mask > 0 and m_ok.any():
            tgt = cls[m_ok]
            nll = -torch.log(res["mask_probs"][m_ok].clamp_min(1e-6)).gather(1, tgt[:, None])[:, 0]
            loss = loss + cfg.lambda_mask * (nll * fg_w[tgt] * mask_w[m_ok]).mean()
        if ext and cfg.lambda_dynamic > 0 and m_ok.any():
            p = res["dynamic_prob"][m_ok].clamp(1e-5, 1 - 1e-5)
            loss = loss + cfg.lambda_dynamic * F.binary_cross_entropy(p, dyn[m_ok], weight=mask_w[m_ok])
        if ext and cfg.lambda_cos > 0:
            # the first ``cos_points`` samples = whole rays from the front of a batch of random rays
            # (random indexing of the 18 strided feature tensors cost ~5 % of a step)
            loss = loss + cfg.lambda_cos * cosine_separation(res["static_space"], res["dynamic_space"])
        optim.zero_grad(set_to_none=True)
        loss.backward()
        optim.step()
        step += 1
        now = time.perf_counter()
        train_s += now - t_mark
        t_mark = now
        lv = float(loss_rgb.detach())
        loss_ema = running_average(loss_ema, lv)
        if train_s - last_log >= cfg.log_every_s:
            last_log = train_s
            p = -10 * math.log10(max(loss_ema, 1e-10))
            curve.append({"step": step, "train_s": round(train_s, 2), "train_psnr": round(p, 2), "lr": lr,
                          "ground_shortfall": None if shortfall_ema is None else round(shortfall_ema, 4),
                          "air_share": None if air_ema is None else round(air_ema, 4),
                          "air_prior_steps": prior_steps})
            msg = f"{model.kind} step {step} {train_s:.0f}s train PSNR {p:.2f} dB lr {lr:.2e}"
            if shortfall_ema is not None:
                msg += f" ground shortfall {shortfall_ema:.1%}, rays in the air {air_ema:.1%}"
            if interactive:
                print(f"\r{msg}   ", end="", file=sys.stderr, flush=True)
            log.info(msg)
        if ckpt and train_s - last_ckpt >= cfg.checkpoint_every_s:
            last_ckpt = train_s
            save_checkpoint(ckpt, model, optim, step, train_s, cfg, _extra(bounds, sizing, curve, gen))
            t_mark = time.perf_counter()
    if interactive:
        print(file=sys.stderr)
    enc.set_scale_weights(torch.ones(enc.n_scales))  # a budget cut short mid-schedule renders every scale
    model.eval()
    if ckpt:
        save_checkpoint(ckpt, model, optim, step, train_s, cfg, _extra(bounds, sizing, curve, gen))
    return DynamicFitResult(model, step, train_s, curve, bounds, sizing, shortfall_ema, air_ema, prior_steps, cfg)


def gate_run_order(dynamic: torch.Tensor, lead: int) -> torch.Tensor:
    """Order (R,) of a batch's rays for the gated extended encoding: the first ``lead`` rays as drawn (those
    ``L_cos`` reads), then the other static rays, then the other dynamic ones (``dynamic`` (R,) bool, True
    inside a person box), each run in its drawn order. The encoding samples points in these runs without
    permuting them (:meth:`fields.kplanes.KPlanesEncoding._forward_split`); the losses are means over rays
    and the trainer hands the sampler the order (``jitter_rows``), so a step's loss and gradients are the
    same in any order."""
    lead = min(max(int(lead), 0), dynamic.shape[0])
    rest = torch.argsort(dynamic[lead:].to(torch.uint8), stable=True) + lead
    return torch.cat([torch.arange(lead, device=dynamic.device), rest])


def background_pose_grad(origins: torch.Tensor, dirs: torch.Tensor, background: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    """The same corrected rays (R, 3) each, but only the rays where ``background`` (R,) bool is set pass
    gradients back to the pose correction; the others render through it as a constant."""
    keep = background[:, None]
    return torch.where(keep, origins, origins.detach()), torch.where(keep, dirs, dirs.detach())


def _extra(bounds, sizing, curve, gen) -> dict:
    return {"bounds": bounds.to_json() if bounds else None, "sizing": sizing, "curve": curve, "rng": gen.get_state()}


def evaluate_dynamic(model: DynamicModel, dd: DynamicFlightData, indices: list[int], min_box_px: float = 6.0,
                     out_dir: Path | None = None, poses: dict[int, np.ndarray] | None = None) -> dict:
    """Held-out PSNR / SSIM of frames rendered at their own pose and time (mean appearance), PSNR
    inside the person boxes (``box_psnr``: where the scene moves) and outside them (``bg_psnr``:
    the static background), the boxes' pixel fraction, and the mask's boxes (synthesis rules,
    ``boxes_from_probabilities``): IoU of the best box per label box >= ``min_box_px``, and recall /
    precision at IoU >= 0.5 (same class) for people >= ``min_box_px`` tall. ``poses``: frame index ->
    OpenCV ``cam_from_world`` in the field's world to render that frame at instead (e.g. aligned by
    :func:`fields.heldout_poses.align_heldout_poses`); other frames get their drift-corrected telemetry pose."""
    import cv2

    data = dd.data
    t01 = dd.t01()
    rows, ious, box_err, bg_err = [], [], [], []
    agreement = None  # synthesis-style matching: IoU >= 0.5, same class, people >= min_box_px tall
    for i in indices:
        # a recorded frame: at its telemetry pose, drift-corrected when the model learned a correction
        pose = poses[i] if poses and i in poses else model.field_pose(data.cam_from_world[i], float(t01[i]))
        r = model.render_image(data.camera, pose, float(t01[i]))
        gt = data.images[i].numpy()
        row = {"frame": data.names[i], "t01": float(t01[i]), "psnr": psnr(r["rgb"], gt), "ssim": ssim(r["rgb"], gt)}
        inside = data.masks[i].numpy() > 0
        sq = ((np.clip(r["rgb"], 0, 1) - gt / 255.0) ** 2).mean(-1)
        if inside.any():
            row["box_psnr"] = psnr(r["rgb"], gt, valid=inside)
            box_err.append(float(sq[inside].mean()))
        if not inside.all():
            row["bg_psnr"] = psnr(r["rgb"], gt, valid=~inside)
            bg_err.append(float(sq[~inside].mean()))
        row["box_fraction"] = float(inside.mean())
        if bool(data.has_mask[i]):
            every_truth = label_boxes(data.boxes[i])
            truth = [t for t in every_truth if min(t.x1 - t.x0, t.y1 - t.y0) >= min_box_px]
            predicted = boxes_from_probabilities(r["mask_probs"])  # the synthesis rules
            ious += match_boxes(truth, predicted)
            matched = match_detections(predicted, every_truth, min_truth_height_px=min_box_px)
            agreement = matched if agreement is None else agreement + matched
            row["boxes"] = len(predicted)
            row["max_foreground"] = float(1.0 - r["mask_probs"][..., 0].min())
        rows.append(row)
        if out_dir:
            out_dir.mkdir(parents=True, exist_ok=True)
            both = np.concatenate([(np.clip(r["rgb"], 0, 1) * 255).astype(np.uint8), gt], axis=1)
            cv2.imwrite(str(out_dir / f"{Path(data.names[i]).stem}_render_vs_truth.png"),
                        cv2.cvtColor(both, cv2.COLOR_RGB2BGR))
    return {"frames": rows, "psnr": float(np.mean([r["psnr"] for r in rows])) if rows else None,
            "ssim": float(np.mean([r["ssim"] for r in rows])) if rows else None,
            "box_psnr": _pooled_psnr(box_err), "bg_psnr": _pooled_psnr(bg_err),
            "box_fraction": float(np.mean([r["box_fraction"] for r in rows])) if rows else None,
            "box_iou_mean": float(np.mean(ious)) if ious else None, "boxes_evaluated": len(ious),
            "box_iou_ge_0.5": float(np.mean(np.asarray(ious) >= 0.5)) if ious else None,
            "mask_recall": agreement.recall if agreement else None,
            "mask_precision": agreement.precision if agreement else None}


def _pooled_psnr(mse_per_frame: list[float]) -> float | None:
    """PSNR (dB) of the frames' mean MSE (pixels pooled per frame), None without frames."""
    return float(-10 * np.log10(max(np.mean(mse_per_frame), 1e-10))) if mse_per_frame else None


def write_dynamic_fit_json(path: Path, result: DynamicFitResult, heldout: dict | None,
                           kind_choice: dict | None = None) -> None:
    n = result.model.param_count()
    payload = {"kind": result.model.kind, "sampler": "stratified", "steps": result.step,
               "train_s": round(result.train_s, 2), "params": n, "mb": round(n * 4 / 1e6, 2),
               "planes": result.model.field_config.planes.to_json(), "sizing": result.sizing,
               "bounds": result.bounds.to_json() if result.bounds else None, "heldout": heldout,
               "kind_choice": kind_choice, "curve": result.curve,
               "config": asdict(result.config) if result.config else None,
               "ground_shortfall": result.ground_shortfall, "air_share": result.air_share,
               "air_prior_steps": result.air_prior_steps,
               "pose_drift": result.model.pose_drift.summary() if result.model.pose_drift is not None else None}
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(payload, indent=1, default=float) + "\n")
    os.replace(tmp, path)
