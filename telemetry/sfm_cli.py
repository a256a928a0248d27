"""``uavsim import-photos DIR OUT`` and ``uavsim sfm-photos FLIGHT``: geotagged photos → posed flight."""

from __future__ import annotations

import logging
from pathlib import Path

log = logging.getLogger(__name__)


def register(subparsers) -> None:
    p = subparsers.add_parser("import-photos", help="geotagged photos (EXIF GPS) → a recorded flight with "
                              "position priors (positions.csv)")
    p.add_argument("src", type=Path, metavar="DIR", help="folder of JPEG photos with EXIF GPS")
    p.add_argument("out", type=Path, metavar="OUT", help="new flight folder")
    p.add_argument("--gps-sigma-h", type=float, default=3.0, help="horizontal GPS 1-sigma, m")
    p.add_argument("--gps-sigma-v", type=float, default=5.0, help="vertical GPS 1-sigma, m")
    p.add_argument("--focal-px", type=float, default=None, help="override the EXIF focal length, px")
    p.set_defaults(func=run_import)

    s = subparsers.add_parser("sfm-photos", help="SfM on an imported-photos flight (positions.csv priors) → "
                              "derived/poses.json, colmap/, transforms.json, points.ply, sfm_report.json")
    s.add_argument("flight", type=Path, metavar="FLIGHT")
    s.add_argument("--max-image-size", type=int, default=None, help="longest side for SIFT, px (1200)")
    s.add_argument("--max-features", type=int, default=None, help="SIFT features per image (4096)")
    s.add_argument("--fixed-intrinsics", action="store_true", help="do not refine focal length/distortion")
    s.add_argument("--seed", type=int, default=None, help="random seed (0)")
    s.add_argument("--threads", type=int, default=None, help="worker threads (-1: all cores)")
    s.set_defaults(func=run_sfm_photos)


def run_import(args) -> int:
    from telemetry.exif import import_photos

    summary = import_photos(args.src, args.out, args.gps_sigma_h, args.gps_sigma_v, args.focal_px)
    print(f"{args.out}: {summary['frames']} frames ({summary['with_gps']} with GPS), focal "
          f"{summary['focal_px']:.1f} px ({summary['intrinsics_source']}); skipped {len(summary['skipped'])}")
    return 0


def run_sfm_photos(args) -> int:
    from telemetry.sfm import SfmOptions
    from telemetry.sfm_flight import refine_flight, with_options

    options = with_options(SfmOptions(refine_intrinsics=not args.fixed_intrinsics),
                           max_image_size=args.max_image_size, max_num_features=args.max_features,
                           seed=args.seed, num_threads=args.threads)
    result = refine_flight(args.flight, options=options)
    rep = result.report
    print(f"{args.flight}: {result.num_refined}/{len(result.frames)} frames refined by SfM, mean reprojection "
          f"{rep.get('mean_reprojection_px') or float('nan'):.2f} px, {len(result.points_xyz)} points"
          + ("" if rep.get("ok") else f"; SfM failed: {rep.get('reason')}"))
    for f in result.frames:
        if f.source != "sfm":
            print(f"  {f.frame}: {f.reason}")
    return 0
