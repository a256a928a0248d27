"""The finest-footprint map and the hash-level weights it implies (fields.footprint)."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from fields.data import load_flight
from fields.field import FieldConfig, StaticField
from fields.footprint import footprint_map, level_weights
from fields.training import FitConfig, fit, load_checkpoint
from telemetry.camera import Camera, Mount
from telemetry.frames import orbit_pose

TINY = dict(iters=20, budget_s=None, batch_rays=256, n_samples=16, budget_mb=1.0, threads=1,
            log_every_s=1e9, checkpoint_every_s=1e9, occupancy_warmup=5, occupancy_every=5)


def test_nadir_camera_footprint_is_height_over_focal_length_and_unseen_cells_take_the_coarsest():
    cam = Camera.from_fov(64, 48, 60.0, Mount(pitch_deg=-90))
    T = orbit_pose(20.0, 0.0, -90.0, 0.0)  # 20 m straight above the origin, looking down
    fp = footprint_map(cam, [T], (-40.0, -40.0), (40.0, 40.0), 0.0, cells=(8, 8), step_px=1)
    f = 0.5 * (cam.fx + cam.fy)
    centre = fp[3:5, 3:5]
    # under the camera a pixel spans height / f metres (the rays there are nearly vertical)
    assert centre.min() == pytest.approx(20.0 / f, rel=0.02)
    # the view is ~23 x 17 m: the box's corner cells are unseen and take the coarsest footprint seen
    assert fp[0, 0] == fp.max() > centre.max() and np.isfinite(fp).all()


def test_footprint_map_refuses_an_empty_box_and_cameras_that_miss_it():
    cam = Camera.from_fov(32, 24, 60.0, Mount(pitch_deg=-90))
    T = orbit_pose(20.0, 0.0, -90.0, 0.0)
    with pytest.raises(ValueError, match="hi > lo"):
        footprint_map(cam, [T], (0.0, 0.0), (0.0, 5.0), 0.0)
    with pytest.raises(ValueError, match="no training ray"):
        footprint_map(cam, [T], (500.0, 500.0), (600.0, 600.0), 0.0)


def test_level_weights_hand_values():
    logp = torch.full((4, 4), math.log(0.1))  # 10 cm everywhere
    cells = torch.tensor([0.025, 0.05, 0.1, 1.0])
    w = level_weights(torch.rand(3, 2), logp, cells)
    expect = torch.erf(math.sqrt(12 / 8) * cells / 0.1)
    assert torch.allclose(w, expect.expand(3, -1), atol=1e-6)
    assert w[0, 2] == pytest.approx(0.9167, abs=1e-3)  # a cell as wide as the footprint keeps 92 %
    assert w[0, 3] == pytest.approx(1.0, abs=1e-6)


@settings(max_examples=40, deadline=None)
@given(st.floats(1e-4, 1e3), st.floats(1e-4, 1e3), st.floats(-1.0, 2.0), st.floats(-1.0, 2.0))
def test_level_weights_are_in_0_1_and_shrink_as_the_footprint_grows(cell, footprint, x, y):
    """Any footprint, any point (outside the box too): weights in (0, 1], finite, monotone."""
    cells = torch.tensor([cell])
    xy = torch.tensor([[x, y]])
    w_fine = level_weights(xy, torch.full((2, 2), math.log(footprint)), cells)
    w_coarse = level_weights(xy, torch.full((2, 2), math.log(footprint * 2)), cells)
    assert torch.isfinite(w_fine).all() and 0 <= w_coarse.item() <= w_fine.item() <= 1.0


def _field(footprint: bool, encoding: str = "hash") -> StaticField:
    torch.manual_seed(0)
    return StaticField(FieldConfig(aabb_lo=(-10.0, -10.0, -1.0), aabb_hi=(10.0, 10.0, 3.0), encoding=encoding,
                                   resolutions=[(4, 4, 2), (16, 16, 4), (64, 64, 16)], log2_table=10,
                                   footprint_cells=(8, 8) if footprint else None))


def test_a_map_finer_than_every_level_leaves_the_field_as_without_one():
    plain, damped = _field(False), _field(True)
    damped.load_state_dict({**plain.state_dict(), "log_footprint": torch.full((8, 8), math.log(1e-6))})
    pts = torch.rand(200, 3) * torch.tensor([20.0, 20.0, 4.0]) - torch.tensor([10.0, 10.0, 1.0])
    s0, g0 = plain.geometry(pts)
    s1, g1 = damped.geometry(pts)
    assert torch.allclose(s0, s1) and torch.allclose(g0, g1)


def test_a_coarse_map_damps_only_the_fine_levels_and_gradients_stay_finite():
    f = _field(True)
    f.set_footprint(np.full((8, 8), 1.0, np.float32))  # 1 m: the finest level (0.31 m cells) is damped
    x01 = torch.rand(100, 3)
    with torch.no_grad():
        plain = f.encoding(x01).view(100, 3, -1)
        damped = f.encode(x01).view(100, 3, -1)
    w = level_weights(x01[:, :2], f.log_footprint, f.level_cell_m)  # cells 5, 1.25, 0.31 m
    assert torch.allclose(damped, plain * w[:, :, None])
    assert (w[:, 0] > 0.999).all() and (w[:, 2] < 0.5).all()
    sigma, _ = f.geometry(f.lo + torch.rand(100, 3) * (f.hi - f.lo))
    sigma.sum().backward()
    assert all(torch.isfinite(p.grad).all() for p in f.parameters() if p.grad is not None)


def test_set_footprint_checks_its_input_and_planes_cannot_take_a_map():
    f = _field(True)
    for bad in (np.ones((4, 4)), np.zeros((8, 8)), np.full((8, 8), np.nan)):
        with pytest.raises(ValueError, match="footprint map"):
            f.set_footprint(bad)
    with pytest.raises(ValueError, match="no footprint map"):
        _field(False).set_footprint(np.ones((8, 8)))
    with pytest.raises(ValueError, match="encoding='hash'"):
        _field(True, encoding="planes")


def test_fit_with_the_footprint_map_saves_it_and_renders_identically_after_loading(tmp_path, tiny_flight):
    d = load_flight(tiny_flight)
    res = fit(d, FitConfig(**TINY, level_footprint=True, footprint_cells=16), out_dir=tmp_path)
    fp = res.model.field.log_footprint.exp()
    assert fp.shape == (16, 16) and (fp > 0).all() and fp.min() < fp.max()
    assert any("footprint" in line for line in res.sizing.reasoning)
    T = orbit_pose(50, 10, -80, 30)
    a = res.model.render_image(d.camera, T)
    model, _ = load_checkpoint(tmp_path / "static.pt")
    assert torch.equal(model.field.log_footprint, res.model.field.log_footprint)
    b = model.render_image(d.camera, T)
    assert np.array_equal(a["rgb"], b["rgb"]) and np.isfinite(a["rgb"]).all()
