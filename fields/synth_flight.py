"""``uavsim synth FLIGHT``: novel views of a fitted flight → labelled synthetic set → Real/Synthetic/R+S.

Reads ``derived/poses.json`` and the fitted field ``derived/fields/static.pt``; writes
``derived/synth/`` (see :mod:`fields.synthesis`) and ``derived/datasets/{real,synthetic,r+s}/``.
Real labels come from the flight's ``labels/`` (self-labelling with a detector happens before,
in the agent's processing step, when a flight has none).
"""

from __future__ import annotations

import logging
from pathlib import Path

log = logging.getLogger(__name__)


def synthesize_flight(flight: str | Path, altitudes_m: tuple[float, ...] = (35.0, 40.0, 45.0, 50.0),
                      count: int = 0, seed: int = 0, max_outside_fraction: float = 0.1) -> dict:
    """Render ``count`` novel views (0: as many as the real training frames) and build the datasets."""
    from export.paper_datasets import build_paper_datasets, labelled_samples, read_class_names
    from fields.field_views import FieldViewRenderer
    from fields.novel_poses import NovelPoseOptions, static_novel_poses
    from fields.synthesis import synthesize
    from fields.training import load_checkpoint
    from telemetry.posesfile import PosesFile

    flight = Path(flight)
    derived = flight / "derived"
    checkpoint = derived / "fields" / "static.pt"
    if not checkpoint.is_file():
        raise FileNotFoundError(f"{checkpoint}: no fitted field (run `uavsim fit {flight}` first)")
    poses = PosesFile.load(derived / "poses.json")
    if not (flight / "labels").is_dir():
        raise FileNotFoundError(f"{flight}/labels: the real frames need labels (human or self-labelled)")
    names = read_class_names(flight / "classes.txt")
    model, _ = load_checkpoint(checkpoint)
    renderer = FieldViewRenderer(model, n_classes=len(names))
    real = labelled_samples(flight / "frames", flight / "labels")
    count = count or max(1, len(real) - len(real) // 5)
    novel = static_novel_poses(poses.camera, [e.cam_from_world for e in poses.posed()],
                               NovelPoseOptions(altitudes_m=tuple(altitudes_m), count=count, seed=seed,
                                                max_outside_fraction=max_outside_fraction),
                               ground_z=model.background.ground_z)
    kept = [p for p in novel if p.kept]
    dropped = [{"altitude_m": p.altitude_m, "pitch_deg": round(p.pitch_deg, 1), "reason": p.reason}
               for p in novel if not p.kept]
    if not kept:
        raise ValueError("no novel pose stays inside the region the real frames observed; lower the altitudes "
                         "or raise the outside-fraction limit")

    def progress(i, n):
        if i % 10 == 0 or i == n:
            log.info("synthesised %d/%d views", i, n)

    report = synthesize(renderer, poses.camera, poses.origin, [p.entry() for p in kept], derived / "synth",
                        names, dropped=dropped, progress=progress)
    synthetic = labelled_samples(derived / "synth" / "images", derived / "synth" / "labels")
    sets = build_paper_datasets(real, synthetic, derived / "datasets", names, seed=seed)
    return {"images": report.images, "boxes": report.boxes, "boxes_per_class": report.boxes_per_class,
            "empty_images": report.empty_images, "dropped_poses": len(dropped),
            "images_per_minute": round(report.images_per_minute, 2),
            "datasets": {k: str(v) for k, v in sets.items()}}


def register(subparsers) -> None:
    p = subparsers.add_parser("synth", help="novel views of a fitted flight → labelled synthetic data and datasets")
    p.add_argument("flight", type=Path)
    p.add_argument("--altitudes", default="35,40,45,50", help="altitudes above ground, m, comma-separated")
    p.add_argument("--count", type=int, default=0, help="views to render (0: as many as real training frames)")
    p.add_argument("--max-outside", type=float, default=0.1,
                   help="drop views showing more than this fraction of unobserved ground")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=run_cli)


def run_cli(args) -> int:
    from agent.replay import parse_altitudes

    if args.count < 0:
        raise ValueError(f"--count must be >= 0, got {args.count}")
    s = synthesize_flight(args.flight, parse_altitudes(args.altitudes), args.count, args.seed, args.max_outside)
    print(f"{args.flight}/derived/synth: {s['images']} views, {s['boxes']} boxes {s['boxes_per_class']}, "
          f"{s['dropped_poses']} poses dropped; datasets: {', '.join(s['datasets'])}")
    return 0
