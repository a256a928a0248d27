"""Rendering shortcuts (skip grid, colour/mask only where the weight matters), the mask grid and
the mask-positive ray oversampling."""

import numpy as np
import pytest
import torch

from fields.data import load_flight
from fields.field import FieldConfig
from fields.model import SamplerConfig, StaticModel
from fields.training import FitConfig, build_model, fit, positive_pixels
from telemetry.camera import Camera, Mount
from telemetry.frames import orbit_pose

LO, HI = (-10.0, -10.0, -0.5), (10.0, 10.0, 5.0)


def _thin_ground_model(counter: list) -> StaticModel:
    """A model whose density is a 0.3 m thick ground layer plus a 1 m cube "person" at the origin;
    geometry features vary with position, so colours and mask differ across the image."""
    cfg = FieldConfig(aabb_lo=LO, aabb_hi=HI, resolutions=[(4, 4, 2)], log2_table=8, n_images=1)
    m = StaticModel(cfg, SamplerConfig("stratified", 48, grid_shape=(40, 40, 22)), 0.0, 20.0).eval()
    torch.manual_seed(0)
    for p in m.field.parameters():
        p.data.normal_(0, 0.5)

    def geometry(points):
        counter.append(points.shape[0])
        z = points[:, 2]
        person = (points[:, :2].abs() < 0.5).all(-1) & (z < 1.0)
        sigma = torch.where((z.abs() < 0.15) | person, torch.full_like(z, 40.0), torch.zeros_like(z))
        geo = torch.sin(points @ torch.linspace(0.3, 2.0, 3 * 15).view(3, 15))
        return sigma, geo

    m.field.geometry = geometry
    m.field.density = lambda p: geometry(p)[0]
    return m


def test_skip_grid_render_matches_exact_render_and_skips_empty_air():
    calls: list = []
    m = _thin_ground_model(calls)
    cam = Camera.from_fov(64, 48, 70.0, Mount(pitch_deg=-80))
    T = orbit_pose(30, 5, -80, 40)
    fast = m.render_image(cam, T)
    n_fast = sum(calls[1:])  # calls[0]: building the skip grid
    grid_share = float(m.skip_grid.float().mean())
    calls.clear()
    m.sampler_config.skip_threshold, m.sampler_config.min_weight = 0.0, 0.0
    exact = m.render_image(cam, T)
    n_exact = sum(calls)
    assert np.abs(fast["rgb"] - exact["rgb"]).max() < 2e-3
    assert np.abs(fast["mask_probs"] - exact["mask_probs"]).max() < 2e-3
    assert np.array_equal(fast["mask"], exact["mask"])
    assert grid_share < 0.3 and n_fast < 0.4 * n_exact


def test_rays_through_empty_air_end_on_the_opaque_floor_with_its_real_colour():
    # nothing but air: every ray exits through the slab's floor, whose (opaque) colour must be evaluated
    m = _thin_ground_model([])
    geometry = m.field.geometry

    def air(points):
        sigma, geo = geometry(points)
        return torch.zeros_like(sigma), geo

    m.field.geometry = air
    m.field.density = lambda p: air(p)[0]
    cam = Camera.from_fov(32, 24, 70.0, Mount(pitch_deg=-80))
    T = orbit_pose(30, 5, -80, 40)
    fast = m.render_image(cam, T)
    assert not m.skip_grid.any()
    m.sampler_config.skip_threshold, m.sampler_config.min_weight = 0.0, 0.0
    exact = m.render_image(cam, T)
    assert np.abs(fast["rgb"] - exact["rgb"]).max() < 1e-5


def test_training_mode_drops_the_skip_grid():
    m = _thin_ground_model([])
    m.build_skip_grid()
    assert m.skip_grid is not None
    m.train()
    assert m.skip_grid is None


def test_mask_grid_config_roundtrip_and_old_checkpoints_read_as_geometry_head():
    cfg = FieldConfig(aabb_lo=LO, aabb_hi=HI, resolutions=[(4, 4, 2)], mask_resolutions=[(4, 4, 2), (8, 8, 4)],
                      log2_table=8, mask_log2_table=8)
    d = cfg.to_json()
    assert FieldConfig.from_json(d) == cfg
    old = {k: v for k, v in d.items() if not k.startswith("mask_")}
    assert FieldConfig.from_json(old).mask_encoding == "geometry"
    desc = StaticModel(cfg, SamplerConfig(), 0.0, 20.0).describe()
    for k in ("skip_threshold", "min_weight"):
        desc["sampler"].pop(k)
    old_model = StaticModel.from_description(desc)  # renders exactly as before the shortcuts
    assert old_model.sampler_config.skip_threshold == 0 and old_model.sampler_config.min_weight == 0


def test_positive_pixels_only_inside_boxes_of_labelled_training_frames():
    masks = torch.zeros(3, 4, 5, dtype=torch.long)
    masks[0, 1, 2] = 1
    masks[1, 3, 4] = 2
    masks[2, 0, 0] = 3
    has = torch.tensor([True, False, True])
    fr, px = positive_pixels(masks.view(3, -1), has, torch.tensor([0, 1]))
    assert fr.tolist() == [0] and px.tolist() == [1 * 5 + 2]


@pytest.mark.parametrize(("rgb_weighted", "pos_until"), [(False, 1.0), (True, 1.0), (True, 0.5)])
def test_mask_budget_and_oversampled_fit(tiny_flight, rgb_weighted, pos_until):
    d = load_flight(tiny_flight)
    tr, _ = d.split(8)
    cfg = FitConfig(iters=15, budget_s=None, batch_rays=256, n_samples=16, budget_mb=1.0, threads=1,
                    log_every_s=1e9, mask_pos_fraction=0.25, rgb_importance_weighted=rgb_weighted,
                    mask_pos_until=pos_until)
    model, _, sizing = build_model(d, tr, cfg, None)
    assert model.field.mask_grid is not None and model.param_count() * 4e-6 <= 1.0
    assert any("mask grid" in r for r in sizing.reasoning)
    res = fit(d, cfg)
    assert res.step == 15 and all(torch.isfinite(p).all() for p in res.model.parameters())


def test_importance_weights_keep_the_loss_unbiased():
    """Drawing n_box of B rays from the box pixels: the weighted batch mean has the same expectation
    as the plain mean over all pixels (exact expectation over the sampling mixture)."""
    from fields.training import importance_weights

    gen = torch.Generator().manual_seed(0)
    loss = torch.rand(1000, generator=gen, dtype=torch.float64)
    pos = torch.zeros(1000, dtype=torch.bool)
    pos[:37] = True
    for batch, n_box in ((1024, 0), (1024, 256), (512, 500)):
        w = importance_weights(batch, n_box, 1000, 37, "cpu").double()
        n_uni = batch - n_box
        weighted = torch.where(pos, w[1], w[0]) * loss
        expectation = (n_uni * weighted.mean() + n_box * weighted[pos].mean()) / batch
        assert float(expectation) == pytest.approx(float(loss.mean()), rel=1e-6)  # float32 weights


def test_rgb_mse_weights_each_ray_by_how_it_was_drawn():
    """Hand-computed: ray errors (per channel) 0.1 and 0.3 -> squared means 0.01 and 0.09. Plain: 0.05.
    Weighted 1.5 (a uniform ray) and 0.5 (a box ray): (1.5 * 0.01 + 0.5 * 0.09) / 2 = 0.03. Uniform
    weights of 1 (no box rays drawn) give the plain mean."""
    from fields.training import importance_weights, rgb_mse

    rgb, target = torch.tensor([[0.1, 0.1, 0.1], [0.3, 0.3, 0.3]]), torch.zeros(2, 3)
    assert torch.isclose(rgb_mse(rgb, target), torch.tensor(0.05))
    assert torch.isclose(rgb_mse(rgb, target, torch.tensor([1.5, 0.5])), torch.tensor(0.03))
    no_box_rays = importance_weights(2, 0, 100, 5, "cpu")
    assert torch.isclose(rgb_mse(rgb, target, no_box_rays[torch.tensor([0, 1])]), torch.tensor(0.05))
