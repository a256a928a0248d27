"""Write an :class:`~telemetry.sfm.SfmResult` into a flight's ``derived/`` folder, in standard formats.

- ``derived/poses.json``: the poses file contract (``telemetry.posesfile``), one entry per frame with
  ``source`` "sfm" or "telemetry", a ``reason`` where SfM did not refine the frame, and the
  per-frame quality numbers as extra keys (``observations``, ``reprojection_px``,
  ``position_change_m``, ``rotation_change_deg``, ``prior_position_enu``...).
- ``derived/colmap/``: the COLMAP binary model (cameras.bin, images.bin, points3D.bin; plus
  rigs.bin/frames.bin as pycolmap 4 writes them), world = ENU metres of the origin. Only frames
  whose SfM pose is kept are registered in it.
- ``derived/transforms.json``: nerfstudio format; ``transform_matrix`` is ``world_from_cam`` in the
  OpenGL camera convention (x right, y up, z back), world = ENU metres (metric, no rescaling);
  ``applied_transform`` records the transform applied to the ENU world (identity) and
  ``ply_file_path`` points at the sparse points.
- ``derived/points.ply``: sparse points, binary little-endian PLY, ``double x y z`` (ENU metres)
  + ``uchar red green blue`` + ``float error`` (mean reprojection error, px) + ``int track_length``.
- ``derived/sfm_report.json``: the run's quality report (registered fraction, mean reprojection
  error, mean track length, per-frame pose change from the priors, reasons).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from telemetry.frames import invert_pose
from telemetry.posesfile import Origin, PoseEntry, PosesFile
from telemetry.sfm import SfmResult

#: OpenCV camera axes (x right, y down, z forward) to OpenGL (x right, y up, z back).
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


def json_safe(value):
    """Numpy scalars/arrays to Python, non-finite floats to None (JSON has no NaN)."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        v = float(value)
        return v if math.isfinite(v) else None
    return value


def _atomic_write_text(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as fh:
        fh.write(text)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def poses_file(result: SfmResult, origin: Origin) -> PosesFile:
    """The poses file contract for a result (every input frame listed, unposed ones with a reason)."""
    entries = [PoseEntry(f.frame, f.t_unix_us, f.cam_from_world, f.source, f.reason, json_safe(f.stats))
               for f in result.frames]
    return PosesFile(origin, result.camera, entries)


def transforms_json(result: SfmResult, origin: Origin, frames_rel: str = "../frames",
                    ply_name: str | None = "points.ply") -> dict:
    """nerfstudio ``transforms.json`` for the posed frames (OpenGL ``world_from_cam``, ENU metres)."""
    cam = result.camera
    k1, k2, p1, p2 = cam.distortion
    frames = []
    for f in result.frames:
        if f.cam_from_world is None:
            continue
        c2w_gl = invert_pose(np.asarray(f.cam_from_world, dtype=np.float64)) @ CV_TO_GL
        frames.append({"file_path": f"{frames_rel}/{f.frame}", "transform_matrix": c2w_gl.tolist(),
                       "source": f.source, "t_unix_us": f.t_unix_us})
    out = {"camera_model": "OPENCV", "fl_x": cam.fx, "fl_y": cam.fy, "cx": cam.cx, "cy": cam.cy,
           "w": cam.width, "h": cam.height, "k1": k1, "k2": k2, "p1": p1, "p2": p2,
           "frames": frames,
           "applied_transform": np.eye(4)[:3].tolist(),
           "uavsim": {"world": "local ENU metres (x east, y north, z up) of origin; metric, not rescaled",
                      "origin": {"lat": origin.lat, "lon": origin.lon, "alt": origin.alt},
                      "camera_convention": "OpenGL (x right, y up, z back), transform_matrix = world_from_cam"}}
    if ply_name:
        out["ply_file_path"] = ply_name
    return out


def write_points_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray, error: np.ndarray | None = None,
                     track_length: np.ndarray | None = None) -> None:
    """Binary little-endian PLY: double x y z, uchar red green blue, float error, int track_length."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    n = len(xyz)
    rgb = np.asarray(rgb, dtype=np.uint8).reshape(-1, 3)
    error = np.full(n, np.nan) if error is None else np.asarray(error, dtype=np.float64)
    track_length = np.zeros(n, int) if track_length is None else np.asarray(track_length)
    if len(rgb) != n or len(error) != n or len(track_length) != n:
        raise ValueError(f"points, colours, errors and track lengths differ in count: {n}, {len(rgb)}, "
                         f"{len(error)}, {len(track_length)}")
    dtype = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("red", "u1"), ("green", "u1"),
                      ("blue", "u1"), ("error", "<f4"), ("track_length", "<i4")])
    data = np.empty(n, dtype=dtype)
    data["x"], data["y"], data["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    data["red"], data["green"], data["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    data["error"] = error
    data["track_length"] = track_length
    header = ("ply\nformat binary_little_endian 1.0\ncomment uavsim sparse SfM points, ENU metres\n"
              f"element vertex {n}\nproperty double x\nproperty double y\nproperty double z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\n"
              "property float error\nproperty int track_length\nend_header\n")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(data.tobytes())
    os.replace(tmp, path)


def read_points_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read ``points.ply`` as written by :func:`write_points_ply`: (xyz float64 (N,3), rgb uint8 (N,3))."""
    raw = Path(path).read_bytes()
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") or end < 0:
        raise ValueError(f"{path}: not a PLY file")
    header = raw[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise ValueError(f"{path}: only binary little-endian PLY is supported")
    types = {"double": "<f8", "float": "<f4", "uchar": "u1", "int": "<i4", "uint": "<u4"}
    fields, n = [], 0
    for line in header:
        parts = line.split()
        if parts[:2] == ["element", "vertex"]:
            n = int(parts[2])
        elif parts and parts[0] == "property":
            fields.append((parts[2], types[parts[1]]))
    data = np.frombuffer(raw, dtype=np.dtype(fields), count=n, offset=end + len(b"end_header\n"))
    xyz = np.stack([data["x"], data["y"], data["z"]], axis=1).astype(np.float64)
    rgb = np.stack([data["red"], data["green"], data["blue"]], axis=1).astype(np.uint8)
    return xyz, rgb


def write_derived(flight_dir: Path, result: SfmResult, origin: Origin, frames_rel: str = "../frames") -> dict:
    """Write poses.json, colmap/, transforms.json, points.ply and sfm_report.json under ``derived/``.

    Returns the paths written, by kind. ``frames_rel`` is the images folder relative to ``derived/``.
    """
    derived = Path(flight_dir) / "derived"
    derived.mkdir(parents=True, exist_ok=True)
    paths = {}
    paths["poses"] = derived / "poses.json"
    poses_file(result, origin).save(paths["poses"])
    paths["points"] = derived / "points.ply"
    write_points_ply(paths["points"], result.points_xyz, result.points_rgb, result.points_error_px,
                     result.points_track_length)
    paths["transforms"] = derived / "transforms.json"
    _atomic_write_text(paths["transforms"],
                       json.dumps(json_safe(transforms_json(result, origin, frames_rel)), indent=1) + "\n")
    if result.reconstruction is not None:
        colmap = derived / "colmap"
        colmap.mkdir(exist_ok=True)
        for old in colmap.glob("*.bin"):
            old.unlink()
        result.reconstruction.write(str(colmap))
        paths["colmap"] = colmap
    report = dict(result.report)
    report["frames"] = [{"frame": f.frame, "source": f.source, "reason": f.reason, **f.stats}
                        for f in result.frames]
    report["outputs"] = {k: str(v.relative_to(derived)) for k, v in paths.items()}
    paths["report"] = derived / "sfm_report.json"
    _atomic_write_text(paths["report"], json.dumps(json_safe(report), indent=1) + "\n")
    return paths
