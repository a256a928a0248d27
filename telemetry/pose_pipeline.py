"""The whole pose step of a flight: telemetry poses, then SfM refinement (``uavsim poses``).

- A flight with a tlog: poses at frame time from telemetry (:mod:`telemetry.poses`); unless SfM is
  off, they seed SfM as priors (position sigma from the expected GPS noise, attitude for the
  initialisation) and frames SfM cannot refine keep their telemetry pose with a reason.
- A flight imported from geotagged photos (``positions.csv``, no tlog): position-only priors.

Writes ``derived/poses.json`` (and with SfM ``colmap/``, ``transforms.json``, ``points.ply``,
``sfm_report.json``); returns a summary for the replay report.
"""

from __future__ import annotations

import logging
from pathlib import Path

from telemetry.frames import camera_center

log = logging.getLogger(__name__)

#: 1-sigma of the telemetry camera centre used as the SfM prior (GPS east, north, up), metres
GPS_SIGMA_M = (1.0, 1.0, 1.5)


def compute_poses(flight: str | Path, sfm: bool = True, seed: int = 0, max_gap_s: float = 0.5,
                  use_gimbal: bool = True, max_image_size: int = 1200) -> dict:
    flight = Path(flight)
    if not (flight / "telemetry.tlog").is_file() and (flight / "positions.csv").is_file():
        if not sfm:
            raise ValueError(f"{flight}: a photo flight has positions only; its poses need SfM (drop --no-sfm)")
        from telemetry.sfm import SfmOptions
        from telemetry.sfm_flight import refine_flight

        result = refine_flight(flight, options=SfmOptions(seed=seed, refine_intrinsics=True,
                                                          max_image_size=max_image_size))
        return _sfm_summary({"frames": len(result.frames), "source": "photos"}, result)

    from telemetry.flightlog import read_flight
    from telemetry.poses import PosesConfig, poses_from_telemetry

    if not max_gap_s > 0:
        raise ValueError(f"max gap must be > 0 s, got {max_gap_s}")
    rec = read_flight(flight)
    if not rec.frames:
        raise ValueError(f"{flight}: no usable frames in frames.csv")
    poses, tracks = poses_from_telemetry(rec.tlog.records, rec.frames, rec.camera,
                                         PosesConfig(max_gap_s=max_gap_s, use_gimbal=use_gimbal))
    n_ok = len(poses.posed())
    summary = {"frames": len(poses.frames), "telemetry_posed": n_ok, "time_source": tracks.time_source,
               "attitude": tracks.attitude_message}
    if n_ok == 0:
        raise ValueError(f"{flight}: no frame could be posed from telemetry (first reason: {poses.frames[0].reason})")
    if not sfm:
        poses.save(flight / "derived" / "poses.json")
        summary["sfm"] = "off"
        return summary
    from telemetry.sfm import Prior, SfmOptions
    from telemetry.sfm_flight import refine_flight

    priors = [Prior(e.frame, e.t_unix_us, None if e.cam_from_world is None else camera_center(e.cam_from_world),
                    sigma_m=GPS_SIGMA_M, cam_from_world=e.cam_from_world) for e in poses.frames]
    result = refine_flight(flight, priors=priors, origin=poses.origin,
                           options=SfmOptions(seed=seed, max_image_size=max_image_size))
    return _sfm_summary(summary, result)


def _sfm_summary(summary: dict, result) -> dict:
    r = result.report
    summary.update({"sfm": "on", "sfm_refined": result.num_refined,
                    "registered_fraction": r.get("registered_fraction"),
                    "mean_reprojection_px": r.get("mean_reprojection_px"),
                    "mean_track_length": r.get("mean_track_length"), "points": int(len(result.points_xyz))})
    reasons = {f.reason for f in result.frames if f.source != "sfm" and f.reason}
    if reasons:
        summary["not_refined_reasons"] = sorted(reasons)[:5]
    return summary
