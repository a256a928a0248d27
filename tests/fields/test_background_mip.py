"""The footprint-aware (mip-mapped) background texture (fields.field.Background, mip=True): hand values
of the level of detail (nadir, grazing, contracted), area averages at coarse levels, the finest level
without a footprint, finite gradients on hard rays, and the checkpoint round trip."""

import math

import pytest
import torch

from fields.field import Background, FieldConfig
from fields.model import SamplerConfig, StaticModel


def ray(origin, direction):
    d = torch.tensor([direction], dtype=torch.float32)
    return torch.tensor([origin], dtype=torch.float32), d / d.norm(dim=-1, keepdim=True)


def test_nadir_level_of_detail_is_the_footprint_in_texels():
    bg = Background(0.0, radius_m=10.0, resolution=64, mip=True)
    o, d = ray([1.0, 2.0, 10.0], [0.0, 0.0, -1.0])
    # footprint 10 m x 0.25 rad = 2.5 m; texture units 2.5 / (2 x 10) = 0.125; a texel is 2 / 64 -> 4 texels
    assert bg.level_of_detail(o, d, 0.25).item() == pytest.approx(2.0, abs=1e-5)


def test_a_ray_60_degrees_off_nadir_reads_one_level_coarser_than_nadir_at_the_same_range():
    bg = Background(0.0, radius_m=100.0, resolution=256, mip=True)
    o_n, d_n = ray([0.0, 0.0, 10.0], [0.0, 0.0, -1.0])
    o_g, d_g = ray([0.0, 0.0, 5.0], [math.sin(math.radians(60)), 0.0, -math.cos(math.radians(60))])  # range 10 m
    lod_n = bg.level_of_detail(o_n, d_n, 0.5).item()  # 5 m: 3.2 texels, level 1.68
    lod_g = bg.level_of_detail(o_g, d_g, 0.5).item()
    assert lod_g - lod_n == pytest.approx(1.0, abs=1e-4)  # the footprint is 1 / cos 60 = 2x longer


def test_contraction_beyond_the_radius_shrinks_the_tangential_footprint():
    bg = Background(0.0, radius_m=10.0, resolution=256, mip=True)
    o_in, d = ray([5.0, 0.0, 10.0], [0.0, 0.0, -1.0])
    o_out, _ = ray([20.0, 0.0, 10.0], [0.0, 0.0, -1.0])  # r = 2: tangential scale (2 - 1/2) / (2 x 2) = 0.375
    gap = bg.level_of_detail(o_out, d, 0.05).item() - bg.level_of_detail(o_in, d, 0.05).item()
    assert gap == pytest.approx(math.log2(0.375 / 0.5), abs=1e-4)


def test_coarse_levels_read_the_area_average_and_no_footprint_reads_the_finest_texel():
    bg = Background(0.0, radius_m=10.0, resolution=16, mip=True)
    checker = (torch.arange(16)[:, None] + torch.arange(16)[None, :]) % 2 * 4.0 - 2.0  # logits +-2 per texel
    with torch.no_grad():
        bg.texture.copy_(checker.expand(1, 3, 16, 16))
    # a texel centre inside the disc: texel (i, j) centre at grid (2 (j + 0.5) / 16 - 1), contracted = xy / (2 R)
    x = (2 * (9 + 0.5) / 16 - 1) * 2 * 10.0
    y = (2 * (6 + 0.5) / 16 - 1) * 2 * 10.0
    o, d = ray([x, y, 10.0], [0.0, 0.0, -1.0])
    fine = bg(o, d)[0, 0].item()
    assert fine == pytest.approx(torch.sigmoid(checker[6, 9]).item(), abs=1e-5)
    coarse = bg(o, d, pixel_rad=1.0)[0, 0].item()  # a huge footprint: the coarsest level
    assert coarse == pytest.approx(0.5, abs=1e-5)  # the mean of sigmoid(2) and sigmoid(-2)
    # footprint 10 m x 0.5 rad = 5 m = 0.25 texture units = 2 texels of 2 / 16: level 1 exactly
    one_level = bg(o, d, pixel_rad=0.5)[0, 0].item()
    assert one_level == pytest.approx(0.5, abs=1e-5)


def test_hard_rays_have_finite_colour_and_gradients():
    bg = Background(0.0, radius_m=20.0, resolution=32, mip=True)
    origins = torch.tensor([[0.0, 0.0, 15.0], [0.0, 0.0, 0.0], [5.0, 5.0, 50.0], [0.0, 0.0, 15.0],
                            [1e4, -1e4, 15.0]])
    dirs = torch.tensor([[0.0, 0.0, -1.0],  # nadir: no ground track
                         [0.0, 0.0, -1.0],  # camera on the ground: zero range
                         [1.0, 0.0, -1e-5],  # grazing, hits the ground kilometres away
                         [1.0, 0.0, 0.0],  # horizon: the sky
                         [0.0, 0.0, -1.0]])  # far outside the disc
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    for pixel_rad in (None, 1e-9, 1e-3, 10.0):
        bg.zero_grad()
        rgb = bg(origins, dirs, pixel_rad)
        assert torch.isfinite(rgb).all() and rgb.min() >= 0 and rgb.max() <= 1
        rgb.sum().backward()
        assert torch.isfinite(bg.texture.grad).all() and torch.isfinite(bg.sky.grad).all()
    assert torch.allclose(bg(origins, dirs, 1e-3)[3], torch.sigmoid(bg.sky))


def test_mip_needs_a_power_of_two_resolution():
    with pytest.raises(ValueError, match="power-of-two"):
        Background(0.0, 10.0, resolution=48, mip=True)
    Background(0.0, 10.0, resolution=48)  # a plain texture does not


def test_a_mip_background_survives_the_checkpoint_description():
    fc = FieldConfig(aabb_lo=(-5.0, -5.0, -0.5), aabb_hi=(5.0, 5.0, 3.0), resolutions=[[8, 8, 4]], features=2,
                     log2_table=10, hidden=8, n_images=1)
    m = StaticModel(fc, SamplerConfig("stratified", 8, 8, (4, 4, 4)), 0.0, 20.0, 32, background_mip=True)
    again = StaticModel.from_description(m.describe())
    assert again.background.mip and again.background.texture.shape[-1] == 32
