"""``uavsim synth FLIGHT``: novel views of a fitted flight → labelled synthetic set → Real/Synthetic/R+S.

Reads ``derived/poses.json`` and the fitted field: ``derived/fields/static.pt`` (static scene: new
altitudes, pitches and orbit radii inside the observed region) or, when only ``dynamic.pt`` is there,
the K-Planes field (dynamic scene, the paper's: N points on the real trajectory, each rendered at t
and t ± Δt with Δt one frame interval). Writes ``derived/synth/`` (see :mod:`fields.synthesis`) and
``derived/datasets/{real,synthetic,r+s}/``.
Real labels come from the flight's ``labels/`` (self-labelling with a detector happens before,
in the agent's processing step, when a flight has none). By default they also decide each synthetic
box's class (``class_source="labels"``, :mod:`fields.label_transfer`): the mask finds the people,
the real labels that see them name the class; in a dynamic scene only real frames within 1.5 frame
intervals of the view's time vote. Static views take their boxes with
:data:`fields.synthesis.HIGH_ALTITUDE_RULES` at the foreground threshold ``uavsim fit`` calibrated on
the held-out frames (:mod:`fields.mask_calibration`; 0.6 without one), dynamic views (flown
altitude) with the default rules.
"""

from __future__ import annotations

import logging
from pathlib import Path

log = logging.getLogger(__name__)


def synthesize_flight(flight: str | Path, altitudes_m: tuple[float, ...] = (35.0, 40.0, 45.0, 50.0),
                      count: int = 0, seed: int = 0, max_outside_fraction: float = 0.1,
                      checkpoint: str | Path | None = None, class_source: str = "labels",
                      mask_threshold: float | None = None) -> dict:
    """Render ``count`` novel views (0: as many as the real training frames) and build the datasets.

    ``checkpoint``: the fitted field (None: ``derived/fields/static.pt``, else ``dynamic.pt``).
    ``altitudes_m`` and ``max_outside_fraction`` apply to static scenes only; a dynamic scene renders
    ceil(count / 3) trajectory points × (t − Δt, t, t + Δt). ``class_source``: "labels" (boxes'
    classes voted by the real labels) or "mask" (the mask head's class). ``mask_threshold``: the
    foreground probability a blob pixel needs. None: for static views the threshold ``uavsim fit``
    calibrated on the held-out frames (``fit.json`` beside the checkpoint; :mod:`fields.mask_calibration`),
    0.6 without one; 0.5 for dynamic views. A well-converged field's masks are sharper and take a
    higher cut (bench/RESULTS.md, synthesis sessions 7-8).
    """
    import dataclasses

    from export.paper_datasets import build_paper_datasets, labelled_samples, read_class_names
    from fields.field_views import DynamicViewRenderer, load_view_renderer
    from fields.label_transfer import LabelledFrames
    from fields.synthesis import HIGH_ALTITUDE_RULES, SynthOptions, synthesize
    from telemetry.posesfile import PosesFile

    if class_source not in ("labels", "mask"):
        raise ValueError(f"class_source must be 'labels' or 'mask', got {class_source!r}")
    flight = Path(flight)
    derived = flight / "derived"
    fields_dir = derived / "fields"
    if checkpoint is not None and not Path(checkpoint).is_file():
        raise FileNotFoundError(f"{checkpoint}: no such fitted field")
    if checkpoint is None and not (fields_dir / "static.pt").is_file() and not (fields_dir / "dynamic.pt").is_file():
        raise FileNotFoundError(f"{fields_dir}: no fitted field, static.pt or dynamic.pt "
                                f"(run `uavsim fit {flight}` first)")
    poses = PosesFile.load(derived / "poses.json")
    if not (flight / "labels").is_dir():
        raise FileNotFoundError(f"{flight}/labels: the real frames need labels (human or self-labelled)")
    names = read_class_names(flight / "classes.txt")
    real = labelled_samples(flight / "frames", flight / "labels")
    count = count or max(1, len(real) - len(real) // 5)
    renderer = load_view_renderer(checkpoint, flight, n_classes=len(names))
    max_dt_us, options = None, SynthOptions()
    if isinstance(renderer, DynamicViewRenderer):
        (kept_entries, frame_interval_us), dropped = _dynamic_poses(poses, count), []
        max_dt_us = int(1.5 * frame_interval_us)
    else:
        kept_entries, dropped = _static_poses(renderer.model.background.ground_z, poses, altitudes_m, count, seed,
                                              max_outside_fraction)
        options = SynthOptions(rules=HIGH_ALTITUDE_RULES)
    threshold_source = "option"
    if mask_threshold is None:
        if not isinstance(renderer, DynamicViewRenderer):
            mask_threshold = calibrated_threshold(Path(checkpoint) if checkpoint else fields_dir / "static.pt")
        threshold_source = "default" if mask_threshold is None else "fit.json"
    if mask_threshold is not None:
        if not 0.0 < mask_threshold < 1.0:
            raise ValueError(f"mask threshold must lie in (0, 1), got {mask_threshold}")
        options = dataclasses.replace(options, rules=dataclasses.replace(options.rules, threshold=mask_threshold))
    log.info("mask threshold %.2f (%s)", options.rules.threshold, threshold_source)

    def progress(i, n):
        if i % 10 == 0 or i == n:
            log.info("synthesised %d/%d views", i, n)

    labels_from = LabelledFrames.from_flight(flight) if class_source == "labels" else None
    if isinstance(renderer, DynamicViewRenderer):  # trajectory views sit on recorded poses
        kept_entries, labels_from = _in_field_world(renderer, kept_entries, labels_from)
    report = synthesize(renderer, poses.camera, poses.origin, kept_entries, derived / "synth",
                        names, options, dropped=dropped, progress=progress, labels_from=labels_from,
                        max_dt_us=max_dt_us)
    synthetic = labelled_samples(derived / "synth" / "images", derived / "synth" / "labels")
    sets = build_paper_datasets(real, synthetic, derived / "datasets", names, seed=seed)
    return {"images": report.images, "boxes": report.boxes, "boxes_per_class": report.boxes_per_class,
            "empty_images": report.empty_images, "dropped_poses": len(dropped),
            "class_source": report.class_source, "relabelled_boxes": report.relabelled_boxes,
            "unvoted_boxes": report.unvoted_boxes,
            "images_per_minute": round(report.images_per_minute, 2),
            "mask_threshold": options.rules.threshold, "mask_threshold_source": threshold_source,
            "datasets": {k: str(v) for k, v in sets.items()}}


def calibrated_threshold(checkpoint: Path) -> float | None:
    """The high-altitude mask threshold ``uavsim fit`` calibrated on the held-out frames, from the
    ``fit.json`` beside ``checkpoint`` (None: no such file, or nothing was calibrated)."""
    import json

    path = checkpoint.with_name("fit.json")
    try:
        fit = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as e:
        log.warning("%s unreadable (%s): default mask threshold", path, e)
        return None
    calib = (fit.get("heldout") or {}).get("mask_threshold") or {}
    value = calib.get("synth_threshold")
    return float(value) if isinstance(value, (int, float)) else None


def _in_field_world(renderer, entries, voters):
    """Trajectory entries and voting frames (recorded telemetry poses) moved into the field's world
    (:meth:`fields.field_views.FieldViewRenderer.field_pose`: a learned pose-drift correction), each
    at its own capture time."""
    import copy
    import dataclasses

    moved = []
    for e in entries:
        e = copy.copy(e)
        e.cam_from_world = renderer.field_pose(e.cam_from_world, e.t_unix_us)
        moved.append(e)
    if voters is not None:
        times = voters.times_us or [None] * len(voters.cam_from_world)
        corrected = [renderer.field_pose(T, t) for T, t in zip(voters.cam_from_world, times, strict=True)]
        voters = dataclasses.replace(voters, cam_from_world=corrected)
    return moved, voters


def _static_poses(ground_z: float, poses, altitudes_m, count: int, seed: int, max_outside_fraction: float):
    """Kept novel pose entries and dropped-pose reasons for a static scene (ground at ``ground_z``, ENU m)."""
    from fields.novel_poses import NovelPoseOptions, static_novel_poses

    novel = static_novel_poses(poses.camera, [e.cam_from_world for e in poses.posed()],
                               NovelPoseOptions(altitudes_m=tuple(altitudes_m), count=count, seed=seed,
                                                max_outside_fraction=max_outside_fraction),
                               ground_z=ground_z)
    kept = [p for p in novel if p.kept]
    dropped = [{"altitude_m": p.altitude_m, "pitch_deg": round(p.pitch_deg, 1), "reason": p.reason}
               for p in novel if not p.kept]
    if not kept:
        raise ValueError("no novel pose stays inside the region the real frames observed; lower the altitudes "
                         "or raise the outside-fraction limit")
    return [p.entry() for p in kept], dropped


def _dynamic_poses(poses, count: int):
    """3N trajectory entries (t − Δt, t, t + Δt; Δt = the median frame interval, µs, also returned)
    for a dynamic scene."""
    import numpy as np

    from fields.novel_poses import dynamic_novel_poses

    times = np.sort([e.t_unix_us for e in poses.posed() if e.t_unix_us is not None])
    steps = np.diff(times)
    steps = steps[steps > 0]
    if steps.size == 0:
        raise ValueError("a dynamic field needs posed frames with at least two distinct capture times")
    frame_interval_us = float(np.median(steps))
    frame_rate_hz = 1e6 / frame_interval_us
    entries = dynamic_novel_poses(poses.posed(), n_points=-(-count // 3), frame_rate_hz=frame_rate_hz)
    log.info("dynamic synthesis: %d trajectory points x 3 times (dt %.3f s)", len(entries) // 3,
             1.0 / frame_rate_hz)
    return entries, frame_interval_us


def register(subparsers) -> None:
    p = subparsers.add_parser("synth", help="novel views of a fitted flight → labelled synthetic data and datasets")
    p.add_argument("flight", type=Path)
    p.add_argument("--altitudes", default="35,40,45,50", help="altitudes above ground, m, comma-separated")
    p.add_argument("--count", type=int, default=0, help="views to render (0: as many as real training frames)")
    p.add_argument("--max-outside", type=float, default=0.1,
                   help="drop views showing more than this fraction of unobserved ground")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--class-source", choices=("labels", "mask"), default="labels",
                   help="boxes' classes: voted by the real labels that see them (default) or the mask head's")
    p.add_argument("--mask-threshold", type=float, default=None,
                   help="foreground probability of a blob pixel (default: static views the threshold `uavsim fit` "
                        "calibrated on the held-out frames, else 0.6; dynamic views 0.5)")
    p.set_defaults(func=run_cli)


def run_cli(args) -> int:
    from agent.replay import parse_altitudes

    if args.count < 0:
        raise ValueError(f"--count must be >= 0, got {args.count}")
    s = synthesize_flight(args.flight, parse_altitudes(args.altitudes), args.count, args.seed, args.max_outside,
                          class_source=args.class_source, mask_threshold=args.mask_threshold)
    print(f"{args.flight}/derived/synth: {s['images']} views, {s['boxes']} boxes {s['boxes_per_class']}, "
          f"{s['dropped_poses']} poses dropped; datasets: {', '.join(s['datasets'])}")
    return 0
