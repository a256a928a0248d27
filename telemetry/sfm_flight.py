"""SfM on a recorded flight folder: read frames, camera and priors, refine, write ``derived/``.

:func:`refine_flight` is what ``uavsim poses FLIGHT`` (telemetry priors, passed in by the caller)
and ``uavsim sfm-photos FLIGHT`` (position-only priors from ``positions.csv``, written by
``uavsim import-photos``) call.
"""

from __future__ import annotations

import csv
import logging
import math
from dataclasses import replace
from pathlib import Path

from telemetry.camera import Camera
from telemetry.exports import write_derived
from telemetry.geodesy import geodetic_to_enu
from telemetry.posesfile import Origin
from telemetry.sfm import Prior, SfmInputError, SfmOptions, SfmResult, refine_poses

log = logging.getLogger(__name__)


def read_frames_csv(flight_dir: Path) -> list[tuple[str, int]]:
    """(frame, t_unix_us) rows of ``frames.csv``."""
    path = Path(flight_dir) / "frames.csv"
    try:
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh))
    except FileNotFoundError:
        raise SfmInputError(f"{path}: no such file (not a recorded flight?)") from None
    out = []
    for k, row in enumerate(rows):
        try:
            out.append((row["frame"], int(row["t_unix_us"])))
        except (KeyError, TypeError, ValueError):
            raise SfmInputError(f"{path}: row {k + 2} must be 'frame,t_unix_us', got {row}") from None
    if not out:
        raise SfmInputError(f"{path}: no frames")
    return out


def read_position_priors(flight_dir: Path, frames: list[tuple[str, int]]) -> tuple[list[Prior], Origin]:
    """Position-only priors from ``positions.csv`` in local ENU; origin = first valid position in time."""
    path = Path(flight_dir) / "positions.csv"
    try:
        with open(path, newline="") as fh:
            rows = {r["frame"]: r for r in csv.DictReader(fh)}
    except FileNotFoundError:
        raise SfmInputError(f"{path}: no such file; position priors come from positions.csv "
                            "(uavsim import-photos) or from telemetry") from None
    except KeyError:
        raise SfmInputError(f"{path}: header must start with 'frame'") from None

    def geo(row):
        try:
            v = (float(row["lat"]), float(row["lon"]), float(row["alt"]))
        except (KeyError, TypeError, ValueError):
            return None
        return v if all(math.isfinite(x) for x in v) else None

    ordered = sorted(frames, key=lambda f: (f[1], f[0]))
    first = next((geo(rows[n]) for n, _ in ordered if n in rows and geo(rows[n])), None)
    if first is None:
        raise SfmInputError(f"{path}: no frame has a valid lat, lon, alt")
    origin = Origin(*first)
    priors = []
    for name, t in frames:
        row = rows.get(name)
        g = geo(row) if row else None
        pos = geodetic_to_enu(*g, (origin.lat, origin.lon, origin.alt)) if g else None
        try:
            sh, sv = float(row["sigma_h_m"]), float(row["sigma_v_m"])
        except (TypeError, KeyError, ValueError):
            sh, sv = 5.0, 10.0
        priors.append(Prior(name, t, pos, (sh, sh, sv)))
    return priors, origin


def refine_flight(flight_dir: Path, priors: list[Prior] | None = None, origin: Origin | None = None,
                  options: SfmOptions | None = None, workdir: Path | None = None) -> SfmResult:
    """Refine a recorded flight's poses and write ``derived/`` (poses.json, colmap/, ...).

    ``priors``/``origin``: telemetry priors in the flight's ENU frame (one per frames.csv row, same
    order) and its geodetic origin; when None, position-only priors are read from positions.csv and
    intrinsics are refined (their EXIF values are only a starting point) unless ``options`` says so.
    """
    flight_dir = Path(flight_dir)
    frames = read_frames_csv(flight_dir)
    camera = Camera.load(flight_dir / "camera.json")
    if priors is None:
        priors, origin = read_position_priors(flight_dir, frames)
        options = options or SfmOptions(refine_intrinsics=True)
    else:
        if origin is None:
            raise SfmInputError("telemetry priors need the flight's geodetic origin")
        if [p.frame for p in priors] != [f for f, _ in frames]:
            raise SfmInputError("priors must list the frames of frames.csv in the same order")
        options = options or SfmOptions()
    images = [flight_dir / "frames" / name for name, _ in frames]
    workdir = Path(workdir) if workdir else flight_dir / "derived" / "sfm_work"
    result = refine_poses(images, camera, priors, workdir, options)
    write_derived(flight_dir, result, origin)
    log.info("SfM: %d of %d frames refined; mean reprojection %s px", result.num_refined, len(frames),
             result.report.get("mean_reprojection_px"))
    return result


def with_options(options: SfmOptions, **changes) -> SfmOptions:
    """A copy of ``options`` with non-None ``changes`` applied (for command-line overrides)."""
    return replace(options, **{k: v for k, v in changes.items() if v is not None})
