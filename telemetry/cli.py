"""``uavsim poses FLIGHT [--no-sfm]`` and ``uavsim tlog FILE.tlog [--json]``."""

from __future__ import annotations

import json
import logging
from pathlib import Path

log = logging.getLogger(__name__)


def register(subparsers) -> None:
    p = subparsers.add_parser("poses", help="telemetry poses (then SfM) -> FLIGHT/derived/poses.json")
    p.add_argument("flight", type=Path, help="recorded flight directory")
    p.add_argument("--no-sfm", action="store_true", help="telemetry poses only (no SfM refinement)")
    p.add_argument("--max-gap", type=float, default=0.5, help="never interpolate across a gap longer than this, s")
    p.add_argument("--no-gimbal", action="store_true", help="ignore gimbal telemetry; use camera.json's mount")
    p.add_argument("--seed", type=int, default=0, help="seed for SfM (same seed, same result)")
    p.set_defaults(func=run_poses)
    t = subparsers.add_parser("tlog", help="summary of a telemetry log")
    t.add_argument("tlog", type=Path, help="a .tlog file (or a flight directory)")
    t.add_argument("--json", action="store_true", help="machine-readable output")
    t.add_argument("--gap", type=float, default=0.5, help="report position/attitude gaps longer than this, s")
    t.set_defaults(func=run_tlog)


def run_poses(args) -> int:
    from telemetry.pose_pipeline import compute_poses

    summary = compute_poses(args.flight, sfm=not args.no_sfm, seed=args.seed, max_gap_s=args.max_gap,
                            use_gimbal=not args.no_gimbal)
    out = Path(args.flight) / "derived" / "poses.json"
    line = f"{out}: {summary.get('telemetry_posed', '-')}/{summary['frames']} frames posed from telemetry"
    if "time_source" in summary:
        line += f" (time source: {summary['time_source']})"
    if summary.get("sfm") == "on":
        reproj = summary["mean_reprojection_px"]
        line += (f"; SfM refined {summary['sfm_refined']}, mean reprojection "
                 f"{'-' if reproj is None else f'{reproj:.2f}'} px, {summary['points']} points")
    print(line)
    for reason in summary.get("not_refined_reasons", []):
        print(f"  not refined: {reason}")
    return 0


def summarize_tlog(path: Path, gap_s: float = 0.5) -> dict:
    """Messages by type, duration, time source, position/attitude gaps of a tlog."""
    from collections import Counter

    from telemetry.mavlink import read_tlog
    from telemetry.poses import TelemetryError, extract_tracks

    res = read_tlog(path)
    recs = res.records
    by_type = Counter(r.type for r in recs)
    by_comp = Counter(f"{r.msg.get_srcSystem()}/{r.msg.get_srcComponent()}" for r in recs)
    mav1 = sum(1 for r in recs if r.raw[0] == 0xFE)
    t = [r.t_unix_us for r in recs]
    summary = {"file": str(path), "messages": len(recs), "mavlink1": mav1, "mavlink2": len(recs) - mav1,
               "duration_s": (max(t) - min(t)) / 1e6 if t else 0.0,
               "start_unix_us": min(t) if t else None, "by_type": dict(by_type.most_common()),
               "by_component": dict(by_comp.most_common()), "unknown_ids": dict(res.unknown_ids),
               "bytes_skipped": res.bytes_skipped, "bad_crc": res.bad_crc, "truncated_tail": res.truncated_tail,
               "problems": res.problems}
    try:
        tracks = extract_tracks(recs)
    except TelemetryError as exc:
        summary.update({"autopilot": None, "time_source": "none", "note": str(exc)})
        return summary
    gap_us = int(gap_s * 1e6)
    cm = tracks.clock_maps.get(tracks.autopilot)
    summary.update({
        "autopilot": list(tracks.autopilot), "time_source": tracks.time_source,
        "boot_epochs": [{"source": e.source, "offset_us": e.offset_us, "drift_ppm": e.drift * 1e6,
                         "samples": e.n_samples, "min_rtt_us": e.rtt_us} for e in (cm.epochs if cm else [])],
        "origin": None if tracks.origin is None else vars(tracks.origin),
        "position_samples": len(tracks.position), "attitude_samples": len(tracks.attitude),
        "attitude_message": tracks.attitude_message, "gimbal_samples": len(tracks.gimbal),
        "position_gaps": [[a, b] for a, b in tracks.position.gaps(gap_us)],
        "attitude_gaps": [[a, b] for a, b in tracks.attitude.gaps(gap_us)],
        "warnings": tracks.warnings})
    return summary


def run_tlog(args) -> int:
    path = Path(args.tlog)
    if path.is_dir():
        path = path / "telemetry.tlog"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such tlog")
    s = summarize_tlog(path, args.gap)
    if s["messages"] == 0:
        raise ValueError(f"{path}: no MAVLink messages could be read ({'; '.join(s['problems']) or 'empty'})")
    if args.json:
        print(json.dumps(s, indent=1))
        return 0
    print(f"{path}: {s['messages']} messages (MAVLink 1: {s['mavlink1']}, 2: {s['mavlink2']}) over "
          f"{s['duration_s']:.1f} s; autopilot {s.get('autopilot')}, time source {s['time_source']}")
    for typ, n in s["by_type"].items():
        rate = n / s["duration_s"] if s["duration_s"] > 0 else 0.0
        print(f"  {typ:32s} {n:8d}  {rate:7.1f}/s")
    for kind in ("position_gaps", "attitude_gaps"):
        for a, b in s.get(kind, []):
            print(f"  {kind[:-5]} gap: {(b - a) / 1e6:.2f} s at unix {a / 1e6:.3f}")
    for p in s["problems"] + s.get("warnings", []):
        print(f"  ! {p}")
    return 0
