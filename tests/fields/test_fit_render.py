"""Fitting, checkpoints and the fit/render commands on a tiny simulated flight."""

import json
import shutil

import cv2
import numpy as np
import pytest
import torch

from agent.cli import main
from fields.data import FlightDataError, box_mask, load_flight
from fields.evaluation import boxes_from_mask, match_boxes, psnr, ssim
from fields.scene import scene_bounds, size_model
from fields.simscene import novel_poses_file
from fields.training import FitConfig, fit, load_checkpoint, upper_box_points
from telemetry.frames import orbit_pose

TINY = dict(iters=30, budget_s=None, batch_rays=256, n_samples=16, budget_mb=1.0, threads=1,
            log_every_s=1e9, checkpoint_every_s=1e9)


def test_load_flight_masks_from_labels(tiny_flight):
    d = load_flight(tiny_flight)
    assert d.n == 8 and d.images.shape == (8, 48, 64, 3)
    assert d.has_mask.all()
    assert d.masks.max() >= 1  # some people
    train, test = d.split(8)
    assert test == [7] and len(train) == 7


def test_box_mask_empty_and_bad_lines():
    assert box_mask("", 10, 8, 3).sum() == 0
    m = box_mask("1 0.5 0.5 0.2 0.25\n", 10, 8, 3)
    assert m.max() == 2 and (m > 0).sum() == 2 * 2
    with pytest.raises(FlightDataError, match="class 7"):
        box_mask("7 0.5 0.5 0.1 0.1", 10, 8, 3)
    with pytest.raises(FlightDataError, match="expected"):
        box_mask("1 0.5", 10, 8, 3)


def test_bounds_and_sizing_from_telemetry(tiny_flight):
    d = load_flight(tiny_flight)
    b = scene_bounds(tiny_flight, d.camera, d.cam_from_world)
    assert b.source == "telemetry" and b.ground_z == 0.0
    assert b.lo[2] < 0 < b.hi[2] <= 0.7 * 15 + 1e-9
    s = size_model(b, "hash", budget_mb=1.0)
    n = sum(min((r[0] + 1) * (r[1] + 1) * (r[2] + 1), 2**s.log2_table) for r in s.resolutions) * s.features
    assert n * 4 <= 1e6
    assert s.finest_cell_m == pytest.approx(b.finest_gsd_m)
    p = size_model(b, "planes", budget_mb=1.0)
    assert p.resolutions[0][0] < p.resolutions[-1][0]


def test_bounds_floor_lies_the_asked_margin_below_the_ground(tiny_flight):
    d = load_flight(tiny_flight)
    default = scene_bounds(tiny_flight, d.camera, d.cam_from_world)
    near = scene_bounds(tiny_flight, d.camera, d.cam_from_world, floor_margin_m=0.1)
    assert default.lo[2] == pytest.approx(-max(0.5, 0.05 * default.hi[2])) and near.lo[2] == pytest.approx(-0.1)
    assert near.hi == default.hi and near.lo[:2] == default.lo[:2]
    assert any("0.10 m below the ground" in n for n in near.notes)
    for bad in (0.0, -0.2, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="floor_margin_m"):
            scene_bounds(tiny_flight, d.camera, d.cam_from_world, floor_margin_m=bad)


def test_bounds_coverage_takes_every_ground_hit(tiny_flight):
    """coverage_pct=100 spans every ground point a training ray saw (+ the margin); 98 trims the tails."""
    from fields.scene import ground_hits

    d = load_flight(tiny_flight)
    hits, _, _ = ground_hits(d.camera, d.cam_from_world, 0.0)
    full = scene_bounds(tiny_flight, d.camera, d.cam_from_world, coverage_pct=100.0, margin_m=0.5)
    trimmed = scene_bounds(tiny_flight, d.camera, d.cam_from_world, coverage_pct=98.0, margin_m=0.5)
    # the tiny flight's rays stay within reach, so every hit counts
    np.testing.assert_allclose(full.lo[:2], hits.min(0) - 0.5)
    np.testing.assert_allclose(full.hi[:2], hits.max(0) + 0.5)
    assert all(f <= t for f, t in zip(full.lo[:2], trimmed.lo[:2], strict=True))
    assert all(f >= t for f, t in zip(full.hi[:2], trimmed.hi[:2], strict=True))
    for bad in (50.0, 100.5):
        with pytest.raises(ValueError, match="coverage_pct"):
            scene_bounds(tiny_flight, d.camera, d.cam_from_world, coverage_pct=bad)


def write_sparse_points(flight, pts: np.ndarray) -> None:
    """``pts`` (N, 3) ENU metres as the flight's SfM point cloud (ASCII ``derived/points.ply``)."""
    (flight / "derived" / "points.ply").write_text(
        f"ply\nformat ascii 1.0\nelement vertex {len(pts)}\nproperty float x\nproperty float y\n"
        "property float z\nend_header\n" + "".join(f"{x} {y} {z}\n" for x, y, z in pts))


def test_bounds_from_sparse_points(tmp_path, tiny_flight):
    flight = tmp_path / "f"
    shutil.copytree(tiny_flight, flight)
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-10, 10, (500, 2)), np.r_[rng.normal(2.0, 0.01, 480), rng.uniform(2, 6, 20)]]
    write_sparse_points(flight, pts)
    d = load_flight(flight)
    b = scene_bounds(flight, d.camera, d.cam_from_world)
    assert b.source == "sparse points"
    assert abs(b.ground_z - 2.0) < 0.05 and b.hi[2] > 5.0
    assert b.lo[2] == pytest.approx(b.ground_z - max(0.5, 0.05 * (b.hi[2] - b.ground_z)))
    # flat ground: the floor 0.1 m below its 0.5th percentile, within a few cm of the ground estimate
    near = scene_bounds(flight, d.camera, d.cam_from_world, floor_margin_m=0.1)
    assert near.ground_z - 0.15 < near.lo[2] <= near.ground_z - 0.1


def test_bounds_floor_clears_sloping_ground_below_the_ground_estimate(tmp_path, tiny_flight):
    """On ground sloping 0 to -3 m the 5th percentile (the ground estimate) is ~ -2.85 m; the floor goes 0.1 m below
    the 0.5th percentile, under all but the lowest 0.5 % of the points, not 0.1 m under the estimate."""
    flight = tmp_path / "f"
    shutil.copytree(tiny_flight, flight)
    rng = np.random.default_rng(1)
    xy = rng.uniform(-10, 10, (2000, 2))
    pts = np.c_[xy, -3.0 * (xy[:, 0] + 10) / 20]
    write_sparse_points(flight, pts)
    d = load_flight(flight)
    b = scene_bounds(flight, d.camera, d.cam_from_world, floor_margin_m=0.1)
    assert b.ground_z > -2.9
    assert b.lo[2] == pytest.approx(np.percentile(pts[:, 2], 0.5) - 0.1, abs=1e-3) and b.lo[2] < b.ground_z - 0.2


def test_black_and_saturated_frames_train_finite(tmp_path, tiny_flight):
    flight = tmp_path / "f"
    shutil.copytree(tiny_flight, flight)
    frames = sorted((flight / "frames").iterdir())
    cv2.imwrite(str(frames[0]), np.zeros((48, 64, 3), np.uint8))
    cv2.imwrite(str(frames[1]), np.full((48, 64, 3), 255, np.uint8))
    (flight / "labels" / (frames[2].stem + ".txt")).write_text("")  # a frame with no people
    d = load_flight(flight)
    res = fit(d, FitConfig(**TINY))
    for p in res.model.parameters():
        assert torch.isfinite(p).all()
    out = res.model.render_image(d.camera, d.cam_from_world[0])
    assert np.isfinite(out["rgb"]).all() and out["rgb"].min() >= 0 and out["rgb"].max() <= 1


@pytest.mark.parametrize("encoding,sampler", [("hash", "occupancy"), ("planes", "stratified")])
def test_checkpoint_roundtrip_renders_identically_and_resumes(tmp_path, tiny_flight, encoding, sampler):
    d = load_flight(tiny_flight)
    cfg = FitConfig(**{**TINY, "encoding": encoding, "sampler": sampler, "occupancy_warmup": 5,
                       "occupancy_every": 5})
    res = fit(d, cfg, out_dir=tmp_path)
    T = orbit_pose(50, 10, -80, 30)
    a = res.model.render_image(d.camera, T)
    model, ck = load_checkpoint(tmp_path / "static.pt")
    b = model.render_image(d.camera, T)
    assert np.array_equal(a["rgb"], b["rgb"]) and np.array_equal(a["mask"], b["mask"])
    assert ck["step"] == 30
    res2 = fit(d, FitConfig(**{**cfg.__dict__, "iters": 40}), out_dir=tmp_path, resume=True)
    assert res2.step == 40
    assert res2.resume_kept == {}  # the same options build the same model: nothing to warn about


def test_resume_keeps_the_checkpoint_model_and_says_what_the_options_would_change(tmp_path, tiny_flight, caplog):
    """A fit resumed with options that build another model (encoding, sampler, size budget) keeps the
    checkpoint's, trains it as what it is (no occupancy updates on a stratified sampler), warns with what
    differs, and ``fit.json`` names the model it trained, not the one asked for."""
    from fields.training import write_fit_json

    d = load_flight(tiny_flight)
    cfg = FitConfig(**{**TINY, "iters": 5, "sampler": "stratified"})
    first = fit(d, cfg, out_dir=tmp_path)
    asked = FitConfig(**{**cfg.__dict__, "iters": 8, "encoding": "planes", "budget_mb": 0.5, "sampler": "occupancy",
                         "occupancy_warmup": 1, "occupancy_every": 1})
    with caplog.at_level("WARNING", logger="fields.training"):
        res = fit(d, asked, out_dir=tmp_path, resume=True)
    assert res.step == 8 and res.model.field_config.encoding == "hash"
    assert res.model.param_count() == first.model.param_count()
    assert res.resume_kept["field.encoding"] == ("hash", "planes")
    warned = [r.getMessage() for r in caplog.records if "keeps the checkpoint's shape" in r.getMessage()]
    assert len(warned) == 1 and "field.encoding: 'hash' -> 'planes'" in warned[0]
    write_fit_json(tmp_path / "fit.json", res, asked, None)
    info = json.loads((tmp_path / "fit.json").read_text())
    assert info["encoding"] == "hash" and info["resume_kept_model"]["field.encoding"] == ["hash", "planes"]
    assert info["sampler"] == "stratified" and info["resume_kept_model"]["sampler.kind"] == ["stratified", "occupancy"]


def test_metrics_on_known_images():
    a = np.zeros((16, 16, 3))
    b = np.full((16, 16, 3), 0.1)
    assert psnr(a, b) == pytest.approx(20.0)
    assert psnr(a, a) == float("inf")
    assert ssim(b, b) == pytest.approx(1.0)
    m = np.zeros((20, 20), np.uint8)
    m[2:8, 3:6] = 1
    m[10:12, 10:12] = 3
    boxes = boxes_from_mask(m, min_area_px=4)
    assert [(bx.class_id, bx.x0, bx.y0, bx.x1, bx.y1) for bx in boxes] == [(0, 3, 2, 6, 8), (2, 10, 10, 12, 12)]
    assert boxes_from_mask(np.zeros((5, 5), np.uint8)) == []
    assert match_boxes(boxes, boxes) == [1.0, 1.0]


def test_cli_fit_then_render(tmp_path, tiny_flight, capsys):
    flight = tmp_path / "f"
    shutil.copytree(tiny_flight, flight)
    assert main(["fit", str(flight), "--kind", "static", "--iters", "20", "--budget-s", "0", "--samples", "16",
                 "--batch-rays", "256", "--budget-mb", "1", "--threads", "1"]) == 0
    info = json.loads((flight / "derived" / "fields" / "fit.json").read_text())
    assert info["steps"] == 20 and info["params"] > 0 and info["mb"] <= 1.0
    assert info["heldout"]["psnr"] > 0 and info["sizing"]["reasoning"]
    # the static fit's floor: 0.1 m below the ground (FitConfig.box_floor_margin_m), and fit.json says so
    assert info["bounds"]["lo"][2] == pytest.approx(-0.1)
    assert any("0.10 m below the ground" in n for n in info["bounds"]["notes"])
    d = load_flight(flight)
    poses = novel_poses_file(d.camera, [orbit_pose(35, 15, -70, 0), orbit_pose(50, 10, -80, 90)])
    poses.frames[0].frame = "000003.png"
    poses.save(tmp_path / "novel.json")
    out = tmp_path / "out"
    assert main(["render", str(flight), "--poses", str(tmp_path / "novel.json"), "--out", str(out), "--masks"]) == 0
    assert (out / "000003.png").is_file() and (out / "pose_00001.png").is_file()
    assert (out / "pose_00001_mask.png").is_file() and (out / "labels" / "pose_00001.txt").is_file()
    img = cv2.imread(str(out / "pose_00001.png"))
    assert img.shape == (48, 64, 3)


def test_cli_errors(tmp_path, tiny_flight, capsys):
    assert main(["fit", str(tmp_path / "nope"), "--kind", "static"]) == 2
    assert "no such flight" in capsys.readouterr().err
    assert main(["fit", str(tmp_path / "nope"), "--kind", "kplanes"]) == 2  # dynamic kinds: same clear error
    assert "no such flight" in capsys.readouterr().err
    assert main(["render", str(tmp_path), "--poses", str(tmp_path / "p.json"), "--out", str(tmp_path / "o")]) == 2
    assert "no such poses file" in capsys.readouterr().err


def test_training_learns_the_frames(tiny_flight):
    d = load_flight(tiny_flight)
    cfg = FitConfig(**{**TINY, "iters": 1})
    before = fit(d, cfg)
    p0 = psnr(before.model.render_image(d.camera, d.cam_from_world[0], with_mask=False)["rgb"], d.images[0].numpy())
    after = fit(d, FitConfig(**{**TINY, "iters": 100, "batch_rays": 256, "lr_final": 1.0}))
    p1 = psnr(after.model.render_image(d.camera, d.cam_from_world[0], with_mask=False)["rgb"], d.images[0].numpy())
    assert p1 > p0 + 3.0, (p0, p1)


def test_heldout_box_iou_uses_label_boxes(tiny_flight):
    d = load_flight(tiny_flight)
    assert len(d.boxes[0]) == len((tiny_flight / "labels" / "000000.txt").read_text().splitlines())
    c, x0, y0, x1, y1 = d.boxes[0][0]
    assert 0 <= x0 < x1 <= 64 and 0 <= y0 < y1 <= 48


def test_upper_box_points_lie_in_the_box_above_the_share():
    lo, hi = torch.tensor([-3.0, 2.0, -1.0]), torch.tensor([5.0, 4.0, 9.0])
    pts = upper_box_points(lo, hi, 2000, 0.3, torch.Generator().manual_seed(0))
    assert pts.shape == (2000, 3)
    assert ((pts >= lo) & (pts <= hi)).all() and float(pts[:, 2].min()) >= -1.0 + 0.3 * 10.0 - 1e-5
    assert float(pts[:, 2].max()) > 8.5 and float(pts[:, 0].min()) < -2.5  # spread over the band
