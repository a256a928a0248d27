"""Geotagged photo import: EXIF GPS / time / focal length → a recorded flight with positions.csv."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import ExifTags, Image
from PIL.TiffImagePlugin import IFDRational

from agent.cli import main as cli_main
from telemetry.camera import Camera
from telemetry.exif import PhotoImportError, focal_length_px, import_photos, read_photo
from telemetry.geodesy import geodetic_to_enu
from telemetry.sfm_flight import read_frames_csv, read_position_priors

SENECA = Path("/work/shared/data/seneca")


def _dms(deg: float):
    d = int(deg)
    m = int((deg - d) * 60)
    s = (deg - d - m / 60) * 3600
    return (IFDRational(d), IFDRational(m), IFDRational(round(s * 1e4), 10000))


def write_photo(path: Path, lat=41.0347, lon=-83.3057, alt=281.5, when="2013:06:04 13:37:29", size=(64, 48),
                model="Canon PowerShot ELPH 300 HS", focal_mm=4.3, plane_res=None, f35=None, orientation=1,
                gps=True):
    rng = np.random.default_rng(abs(hash(path.name)) % 2**32)
    img = Image.fromarray(rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8))
    exif = Image.Exif()
    exif[0x0110] = model
    exif[0x0112] = orientation
    ex = exif.get_ifd(ExifTags.IFD.Exif)
    ex[0x9003] = when
    if focal_mm:
        ex[0x920A] = IFDRational(round(focal_mm * 100), 100)
    if plane_res:
        ex[0xA20E] = IFDRational(round(plane_res * 1000), 1000)
        ex[0xA210] = 2
    if f35:
        ex[0xA405] = f35
    if gps:
        g = exif.get_ifd(ExifTags.IFD.GPSInfo)
        g[1], g[2] = ("N" if lat >= 0 else "S"), _dms(abs(lat))
        g[3], g[4] = ("E" if lon >= 0 else "W"), _dms(abs(lon))
        g[5], g[6] = 0, IFDRational(round(alt * 100), 100)
    img.save(path, exif=exif, quality=95)
    return path


def test_read_photo_gps_time_focal(tmp_path):
    p = write_photo(tmp_path / "a.jpg", plane_res=6071.64 * 64 / 1200)
    info = read_photo(p)
    assert info.lat == pytest.approx(41.0347, abs=1e-7) and info.lon == pytest.approx(-83.3057, abs=1e-7)
    assert info.alt == pytest.approx(281.5)
    assert info.t_unix_us == 1370353049 * 1_000_000  # 2013-06-04 13:37:29 UTC
    assert info.focal_px == pytest.approx(4.3 * 6071.64 / 25.4 * 64 / 1200, rel=1e-3)


def test_focal_length_fallbacks():
    assert focal_length_px({0x920A: 4.3}, "Canon PowerShot ELPH 300 HS", 1200)[0] == pytest.approx(4.3 / 6.17 * 1200)
    f, src = focal_length_px({0xA405: 24}, "unknown cam", 1000)
    assert f == pytest.approx(24 / 36 * 1000) and "35 mm" in src
    assert focal_length_px({}, "unknown", 1000) == (None, "none")


def test_import_sorts_by_time_and_writes_priors(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    write_photo(src / "b.jpg", lat=41.0, lon=-83.0, alt=300.0, when="2013:06:04 13:37:35")
    write_photo(src / "a.jpg", lat=41.0001, lon=-83.0, alt=301.0, when="2013:06:04 13:37:40")  # later
    write_photo(src / "c.jpg", when="2013:06:04 13:37:30", gps=False)
    (src / "notes.txt").write_text("not a photo")
    (src / "broken.jpg").write_bytes(b"\xff\xd8 nope")
    out = tmp_path / "flight"
    summary = import_photos(src, out)
    assert summary["frames"] == 3 and summary["with_gps"] == 2 and "broken.jpg" in summary["skipped"]
    frames = read_frames_csv(out)
    assert [f for f, _ in frames] == ["c.jpg", "b.jpg", "a.jpg"]
    assert [t for _, t in frames] == sorted(t for _, t in frames)
    assert (out / "frames" / "a.jpg").read_bytes() == (src / "a.jpg").read_bytes()
    cam = Camera.load(out / "camera.json")
    assert cam.fx == pytest.approx(4.3 / 6.17 * 64) and (cam.width, cam.height) == (64, 48)
    rows = list(csv.DictReader(open(out / "positions.csv")))
    assert rows[0]["frame"] == "c.jpg" and rows[0]["lat"] == ""
    priors, origin = read_position_priors(out, frames)
    assert (origin.lat, origin.lon, origin.alt) == pytest.approx((41.0, -83.0, 300.0))  # first valid in time
    assert priors[0].finite_position() is None
    np.testing.assert_allclose(priors[1].position_enu, 0.0, atol=1e-6)
    np.testing.assert_allclose(priors[2].position_enu, [0.0, 11.1, 1.0], atol=0.05)
    assert priors[2].sigma_vec() == pytest.approx([3.0, 3.0, 5.0])
    with pytest.raises(PhotoImportError, match="already holds"):
        import_photos(src, out)


def test_import_rejects_bad_folders(tmp_path):
    with pytest.raises(PhotoImportError, match="no such folder"):
        import_photos(tmp_path / "nope", tmp_path / "out")
    (tmp_path / "empty").mkdir()
    with pytest.raises(PhotoImportError, match="no readable photos"):
        import_photos(tmp_path / "empty", tmp_path / "out")
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    write_photo(mixed / "a.jpg", size=(64, 48))
    write_photo(mixed / "b.jpg", size=(48, 64))
    with pytest.raises(PhotoImportError, match="different sizes"):
        import_photos(mixed, tmp_path / "out")


def test_rotated_photo_is_skipped_with_reason(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    write_photo(src / "up.jpg")
    write_photo(src / "rot.jpg", orientation=6)
    summary = import_photos(src, tmp_path / "out")
    assert summary["frames"] == 1 and "orientation" in summary["skipped"]["rot.jpg"]


def test_no_focal_information_gives_a_guess(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    write_photo(src / "a.jpg", model="Mystery", focal_mm=None)
    summary = import_photos(src, tmp_path / "out")
    assert "guess" in summary["intrinsics_source"]
    assert Camera.load(tmp_path / "out" / "camera.json").fx == pytest.approx(32 / math.tan(math.radians(30)))


def test_geodetic_to_enu():
    np.testing.assert_allclose(geodetic_to_enu(41.0, -83.0, 300.0, (41.0, -83.0, 300.0)), 0.0, atol=1e-9)
    e = geodetic_to_enu(41.0, -83.0 + 1e-4, 300.0, (41.0, -83.0, 300.0))
    assert e[0] == pytest.approx(8.42, abs=0.01) and abs(e[1]) < 1e-3
    up = geodetic_to_enu(41.0, -83.0, 350.0, (41.0, -83.0, 300.0))
    np.testing.assert_allclose(up, [0, 0, 50.0], atol=1e-6)


def test_cli_import_photos(tmp_path, capsys):
    src = tmp_path / "src"
    src.mkdir()
    write_photo(src / "a.jpg")
    assert cli_main(["import-photos", str(src), str(tmp_path / "f")]) == 0
    assert "1 frames (1 with GPS)" in capsys.readouterr().out
    assert cli_main(["import-photos", str(tmp_path / "missing"), str(tmp_path / "g")]) == 2
    assert "no such folder" in capsys.readouterr().err


def test_cli_sfm_photos_on_a_flight_without_priors_fails_cleanly(tmp_path, capsys):
    (tmp_path / "frames").mkdir()
    (tmp_path / "frames.csv").write_text("frame,t_unix_us\na.jpg,1\n")
    Camera.from_fov(64, 48, 60).save(tmp_path / "camera.json")
    assert cli_main(["sfm-photos", str(tmp_path)]) == 2
    assert "positions.csv" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.skipif(not SENECA.is_dir(), reason="Seneca photos not present")
def test_seneca_end_to_end(tmp_path):
    from telemetry.sfm_flight import refine_flight

    import_photos(SENECA, tmp_path / "seneca")
    res = refine_flight(tmp_path / "seneca")
    assert res.num_refined >= 21
    assert res.report["mean_reprojection_px"] <= 1.0
    for f in res.frames:
        if f.source == "sfm":
            assert f.stats["position_change_sigma"] < 3.0
        else:
            assert f.reason and "prior_position_enu" in f.stats
    rep = json.loads((tmp_path / "seneca" / "derived" / "sfm_report.json").read_text())
    assert rep["num_registered"] == res.num_refined
