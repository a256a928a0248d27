"""Geotagged photos (EXIF) → a recorded flight with position priors (``uavsim import-photos``).

What the import writes (DESIGN.md §3 recorded-flight layout, no ``telemetry.tlog``)::

    OUT/frames/          the photos, copied byte for byte (EXIF kept), original file names
    OUT/frames.csv       "frame,t_unix_us", sorted by capture time (EXIF time, see below)
    OUT/camera.json      intrinsics from the EXIF focal length (see :func:`focal_length_px`), mount zero
    OUT/positions.csv    "frame,lat,lon,alt,sigma_h_m,sigma_v_m": the position prior of each frame,
                         WGS84 degrees, metres above mean sea level, 1-sigma horizontal / vertical
                         noise in metres; empty lat/lon/alt when the photo has no GPS tag

``positions.csv`` is the contract for position-only priors: a flight that has it and no tlog is
posed by SfM from these priors alone (:func:`telemetry.sfm_flight.refine_flight`); the local ENU
origin is the first frame (in time order) with a valid position.

Capture time: EXIF GPS date/time stamps (UTC) when present, else ``DateTimeOriginal`` (+
``SubSecTimeOriginal``, + ``OffsetTimeOriginal`` when present, else read as UTC), else the file's
modification time; the source is logged.
"""

from __future__ import annotations

import csv
import datetime as dt
import logging
import math
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from telemetry.camera import Camera

log = logging.getLogger(__name__)

#: Sensor widths (mm) of a few common drone / compact cameras, by EXIF Model (lower case).
SENSOR_WIDTH_MM = {
    "canon powershot elph 300 hs": 6.17,
    "canon powershot s100": 7.44,
    "canon powershot s110": 7.44,
    "fc6310": 13.2,       # DJI Phantom 4 Pro
    "fc6310s": 13.2,
    "fc330": 6.17,        # DJI Phantom 4
    "fc300x": 6.17,       # DJI Phantom 3
    "fc220": 6.17,        # DJI Mavic Pro
    "fc7303": 6.4,        # DJI Mini 2
    "l1d-20c": 13.2,      # DJI Mavic 2 Pro (Hasselblad)
    "zenmusex4s": 13.2,
    "gopro hero4 black": 6.17,
    "ilce-6000": 23.5,    # Sony a6000
    "dsc-rx100m2": 13.2,
}

#: Horizontal field of view assumed when nothing in EXIF gives the focal length (refined by SfM).
GUESS_HFOV_DEG = 60.0

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff"}


class PhotoImportError(ValueError):
    """Photos that cannot become a flight (none found, mixed sizes, ...)."""


@dataclass
class PhotoInfo:
    """What EXIF says about one photo. ``lat``/``lon`` degrees, ``alt`` metres AMSL (None: absent)."""

    path: Path
    width: int
    height: int
    t_unix_us: int
    time_source: str
    lat: float | None
    lon: float | None
    alt: float | None
    focal_px: float | None
    focal_source: str
    model: str


def _rational(v) -> float:
    try:
        return float(v)
    except (TypeError, ValueError, ZeroDivisionError):
        return float("nan")


def _dms(values, ref: str | None) -> float | None:
    try:
        d, m, s = (_rational(v) for v in values)
    except (TypeError, ValueError):
        return None
    deg = d + m / 60.0 + s / 3600.0
    if not math.isfinite(deg):
        return None
    return -deg if (ref or "").strip().upper() in ("S", "W") else deg


def focal_length_px(exif_ifd: dict, model: str, width: int) -> tuple[float | None, str]:
    """Focal length in pixels for an image ``width`` px wide, and where it came from.

    In order: FocalLength (mm) × FocalPlaneXResolution (px per unit); FocalLength / sensor width
    from :data:`SENSOR_WIDTH_MM`; FocalLengthIn35mmFilm / 36 mm; else None.
    """
    f_mm = _rational(exif_ifd.get(0x920A))  # FocalLength
    res = _rational(exif_ifd.get(0xA20E))  # FocalPlaneXResolution
    unit = exif_ifd.get(0xA210, 2)  # FocalPlaneResolutionUnit: 2 inch, 3 cm, 4 mm, 5 um
    unit_mm = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}.get(int(unit) if str(unit).isdigit() else 2, 25.4)
    if f_mm > 0 and res > 0 and math.isfinite(f_mm * res):
        return f_mm * res / unit_mm, "exif focal length x focal-plane resolution"
    sensor = SENSOR_WIDTH_MM.get(model.strip().lower())
    if f_mm > 0 and sensor:
        return f_mm / sensor * width, f"exif focal length / sensor width {sensor} mm (table)"
    f35 = _rational(exif_ifd.get(0xA405))  # FocalLengthIn35mmFilm
    if f35 > 0:
        return f35 / 36.0 * width, "exif 35 mm equivalent focal length"
    return None, "none"


def _exif_time(exif, exif_ifd: dict, gps: dict, path: Path) -> tuple[int, str]:
    stamp, date = gps.get(7), gps.get(29)  # GPSTimeStamp, GPSDateStamp
    if stamp and date:
        try:
            h, m, s = (_rational(v) for v in stamp)
            day = dt.datetime.strptime(str(date).strip(), "%Y:%m:%d").replace(tzinfo=dt.UTC)
            t = day + dt.timedelta(hours=h, minutes=m, seconds=s)
            return int(round(t.timestamp() * 1e6)), "exif gps time (UTC)"
        except (ValueError, TypeError):
            pass
    text = exif_ifd.get(0x9003) or exif.get(0x0132)  # DateTimeOriginal, DateTime
    if text:
        try:
            t = dt.datetime.strptime(str(text).strip(), "%Y:%m:%d %H:%M:%S")
            sub = str(exif_ifd.get(0x9291) or "").strip()  # SubSecTimeOriginal
            if sub.isdigit():
                t = t + dt.timedelta(seconds=float("0." + sub))
            off = str(exif_ifd.get(0x9011) or "").strip()  # OffsetTimeOriginal "+02:00"
            tz = dt.UTC
            if len(off) == 6 and off[0] in "+-":
                sign = 1 if off[0] == "+" else -1
                tz = dt.timezone(sign * dt.timedelta(hours=int(off[1:3]), minutes=int(off[4:6])))
            return int(round(t.replace(tzinfo=tz).timestamp() * 1e6)), "exif DateTimeOriginal" + (
                "" if tz is not dt.UTC else " (read as UTC)")
        except ValueError:
            pass
    return int(path.stat().st_mtime * 1e6), "file modification time"


def read_photo(path: Path) -> PhotoInfo:
    """EXIF GPS position, capture time and focal length of one photo (raises OSError if unreadable)."""
    from PIL import ExifTags, Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            width, height = im.size
            exif = im.getexif()
    except UnidentifiedImageError as exc:
        raise OSError(f"{path}: not an image ({exc})") from None
    exif_ifd = dict(exif.get_ifd(ExifTags.IFD.Exif))
    gps = dict(exif.get_ifd(ExifTags.IFD.GPSInfo))
    orientation = exif.get(0x0112, 1)
    if orientation not in (None, 1):
        raise OSError(f"{path}: EXIF orientation {orientation} (rotated image) is not supported; "
                      "save the photo upright first")
    model = str(exif.get(0x0110) or "").strip("\x00 ")
    lat = _dms(gps.get(2), gps.get(1)) if gps.get(2) else None
    lon = _dms(gps.get(4), gps.get(3)) if gps.get(4) else None
    alt = _rational(gps.get(6)) if gps.get(6) is not None else None
    if alt is not None and gps.get(5) in (1, b"\x01"):
        alt = -alt
    if alt is not None and not math.isfinite(alt):
        alt = None
    if lat is not None and not -90.0 <= lat <= 90.0 or lon is not None and not -180.0 <= lon <= 180.0:
        lat = lon = None
    t_us, t_src = _exif_time(exif, exif_ifd, gps, path)
    f_px, f_src = focal_length_px(exif_ifd, model, width)
    return PhotoInfo(path, width, height, t_us, t_src, lat, lon, alt, f_px, f_src, model)


# -- import -------------------------------------------------------------------------------------
def import_photos(src_dir: Path, out_dir: Path, sigma_h_m: float = 3.0, sigma_v_m: float = 5.0,
                  focal_px: float | None = None) -> dict:
    """Copy geotagged photos from ``src_dir`` into a new recorded flight ``out_dir`` (see module doc).

    Returns a summary (frames, with_gps, intrinsics source, skipped files with reasons).
    Raises :class:`PhotoImportError` when nothing usable is found or sizes differ, and refuses to
    overwrite an existing flight.
    """
    src_dir, out_dir = Path(src_dir), Path(out_dir)
    if not src_dir.is_dir():
        raise PhotoImportError(f"{src_dir}: no such folder")
    if (out_dir / "frames.csv").exists():
        raise PhotoImportError(f"{out_dir}: already holds a flight (frames.csv); choose a new folder")
    if not (sigma_h_m > 0 and sigma_v_m > 0 and math.isfinite(sigma_h_m + sigma_v_m)):
        raise PhotoImportError(f"GPS sigmas must be positive, got {sigma_h_m}, {sigma_v_m}")
    files = sorted(p for p in src_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    photos, skipped = [], {}
    for path in files:
        try:
            photos.append(read_photo(path))
        except OSError as exc:
            skipped[path.name] = str(exc)
            log.warning("skipping %s", exc)
    if not photos:
        raise PhotoImportError(f"{src_dir}: no readable photos ({len(skipped)} skipped)")
    sizes = {(p.width, p.height) for p in photos}
    if len(sizes) > 1:
        raise PhotoImportError(f"{src_dir}: photos of different sizes {sorted(sizes)}; import one camera at a time")
    names = [p.path.name for p in photos]
    if len(set(names)) != len(names):
        raise PhotoImportError(f"{src_dir}: duplicate file names")
    photos.sort(key=lambda p: (p.t_unix_us, p.path.name))
    width, height = photos[0].width, photos[0].height
    if focal_px is not None:
        f, f_src = float(focal_px), "given on the command line"
    else:
        known = [p.focal_px for p in photos if p.focal_px]
        if known:
            f, f_src = float(np.median(known)), photos[0].focal_source
        else:
            f = 0.5 * width / math.tan(math.radians(GUESS_HFOV_DEG) / 2.0)
            f_src = f"guess ({GUESS_HFOV_DEG:.0f} deg horizontal field of view), refined by SfM"
    camera = Camera(width, height, f, f, width / 2.0, height / 2.0)
    frames = out_dir / "frames"
    frames.mkdir(parents=True, exist_ok=True)
    for p in photos:
        shutil.copy2(p.path, frames / p.path.name)
    with open(out_dir / "positions.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["frame", "lat", "lon", "alt", "sigma_h_m", "sigma_v_m"])
        for p in photos:
            ok = p.lat is not None and p.lon is not None and p.alt is not None
            w.writerow([p.path.name, f"{p.lat:.9f}" if ok else "", f"{p.lon:.9f}" if ok else "",
                        f"{p.alt:.3f}" if ok else "", sigma_h_m, sigma_v_m])
    camera.save(out_dir / "camera.json")
    # frames.csv last: its presence marks a complete import
    with open(out_dir / "frames.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["frame", "t_unix_us"])
        for p in photos:
            w.writerow([p.path.name, p.t_unix_us])
    with_gps = sum(p.lat is not None and p.alt is not None for p in photos)
    summary = {"frames": len(photos), "with_gps": with_gps, "focal_px": f, "intrinsics_source": f_src,
               "time_source": sorted({p.time_source for p in photos}), "skipped": skipped}
    log.info("imported %d photos (%d with GPS) into %s; focal %.1f px from %s", len(photos), with_gps,
             out_dir, f, f_src)
    return summary
