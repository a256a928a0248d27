"""Ray/box intersection, samplers and the field on hard cases."""

import math

import numpy as np
import pytest
import torch

from fields.field import Background, FieldConfig, StaticField
from fields.model import SamplerConfig, StaticModel, topdown_rays
from fields.samplers import OccupancySampler, StratifiedSampler, ray_box, sample_pdf

LO = torch.tensor([-10.0, -10.0, -0.5])
HI = torch.tensor([10.0, 10.0, 5.0])


def test_ray_box_hits_and_misses():
    o = torch.tensor([[0.0, 0.0, 15.0], [0.0, 0.0, 15.0], [50.0, 0.0, 15.0], [0.0, 0.0, 2.0]])
    d = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    near, far, hit = ray_box(o, d, LO, HI)
    assert hit.tolist() == [True, False, False, True]
    assert torch.allclose(near[0], torch.tensor(10.0)) and torch.allclose(far[0], torch.tensor(15.5))
    assert near[1] == far[1] == 0  # missing rays get an empty segment
    assert near[3] == 0 and torch.allclose(far[3], torch.tensor(10.0))  # starts inside


def test_grazing_rays_from_50m_are_finite():
    # 50 m high, nearly horizontal (0.01 deg below the horizon) and exactly horizontal rays
    ang = math.radians(0.01)
    o = torch.tensor([[0.0, -200.0, 50.0], [0.0, -200.0, 4.0], [0.0, -200.0, 50.0]])
    d = torch.tensor([[0.0, math.cos(ang), -math.sin(ang)], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    near, far, hit = ray_box(o, d, LO, HI)
    assert torch.isfinite(near).all() and torch.isfinite(far).all()
    assert hit.tolist() == [False, True, False]
    edges = StratifiedSampler(16).edges(o, d, LO, HI, train=True)
    assert torch.isfinite(edges).all()
    assert (edges[:, 1:] >= edges[:, :-1]).all()


def test_points_exactly_on_bounds_are_inside():
    cfg = FieldConfig(aabb_lo=tuple(LO.tolist()), aabb_hi=tuple(HI.tolist()), resolutions=[(4, 4, 2)],
                      log2_table=8, density_bias=5.0)
    f = StaticField(cfg)
    pts = torch.stack([LO, HI, torch.tensor([10.0, -10.0, 5.0]), torch.tensor([10.001, 0.0, 0.0])])
    sigma = f.density(pts)
    assert (sigma[:3] > 0).all() and sigma[3] == 0


def test_stratified_edges_cover_segment():
    o = torch.tensor([[0.0, 0.0, 15.0]])
    d = torch.tensor([[0.0, 0.0, -1.0]])
    e = StratifiedSampler(8).edges(o, d, LO, HI, train=False)
    assert torch.allclose(e[0, 0], torch.tensor(10.0)) and torch.allclose(e[0, -1], torch.tensor(15.5))


def test_stratified_jitter_follows_reordered_rays():
    # rays drawn in one order and sampled in another keep the jitter they were drawn with
    gen = torch.Generator().manual_seed(3)
    o = torch.rand(9, 3, generator=gen) * 4 + torch.tensor([0.0, 0.0, 12.0])
    d = torch.nn.functional.normalize(torch.rand(9, 3, generator=gen) - torch.tensor([0.5, 0.5, 1.5]), dim=-1)
    order = torch.randperm(9, generator=gen)
    sampler = StratifiedSampler(6)
    drawn = sampler.edges(o, d, LO, HI, train=True, generator=torch.Generator().manual_seed(7))
    moved = sampler.edges(o[order], d[order], LO, HI, train=True, generator=torch.Generator().manual_seed(7),
                          jitter_rows=order)
    assert torch.equal(moved, drawn[order])
    plain = sampler.edges(o[order], d[order], LO, HI, train=True, generator=torch.Generator().manual_seed(7))
    assert not torch.equal(plain, drawn[order])  # without it the jitter stays with the batch position


def test_sample_pdf_concentrates_near_peak():
    edges = torch.linspace(0, 1, 11).expand(2, 11).contiguous()
    w = torch.zeros(2, 10)
    w[:, 6] = 1.0
    out = sample_pdf(edges, w, 9, train=False)
    inner = out[:, 1:-1]
    assert ((inner >= 0.6) & (inner <= 0.7)).float().mean() > 0.9
    assert out[0, 0] == 0 and out[0, -1] == 1


def test_occupancy_sampler_learns_the_ground():
    s = OccupancySampler((8, 8, 11), n_samples=8, n_coarse=64, decay=0.0, update_fraction=1.0)
    s.update(lambda p: (p[:, 2].abs() < 0.5).float() * 50.0, LO, HI)
    o = torch.tensor([[0.0, 0.0, 15.0]])
    d = torch.tensor([[0.0, 0.0, -1.0]])
    e = s.edges(o, d, LO, HI, train=False)
    mids = 0.5 * (e[0, 1:] + e[0, :-1])
    z = o[0, 2] - mids
    assert ((z > -0.6) & (z < 1.2)).float().mean() > 0.6, z  # most samples near the ground
    state = s.state_dict()
    s2 = OccupancySampler((8, 8, 11), n_samples=8, n_coarse=64)
    s2.load_state_dict(state)
    assert torch.equal(s2.edges(o, d, LO, HI, train=False), e)


def test_a_fresh_occupancy_grid_samples_like_the_stratified_sampler():
    o = torch.tensor([[0.0, 0.0, 15.0], [3.0, -2.0, 12.0]])
    d = torch.nn.functional.normalize(torch.tensor([[0.0, 0.0, -1.0], [0.3, 0.2, -0.9]]), dim=-1)
    occ = OccupancySampler((8, 8, 11), n_samples=8, n_coarse=64).edges(o, d, LO, HI, train=False)
    strat = StratifiedSampler(8).edges(o, d, LO, HI, train=False)
    assert torch.allclose(occ, strat, atol=1e-3)


def test_occupancy_samples_a_faint_person_and_the_ground_behind_it():
    """Evenly over every occupied stretch, not only the first surface: a person of density 0.5/m
    (40 % opaque over its 1 m) above opaque ground keeps samples in both."""
    def density(p):
        ground = (p[:, 2] < 0.0).float() * 1e3
        person = ((p[:, 2] > 1.0) & (p[:, 2] < 2.0)).float() * 0.5
        return ground + person

    s = OccupancySampler((4, 4, 22), n_samples=32, n_coarse=220, update_fraction=1.0)
    s.update(density, LO, HI, full=True)
    o, d = torch.tensor([[0.0, 0.0, 15.0]]), torch.tensor([[0.0, 0.0, -1.0]])
    e = s.edges(o, d, LO, HI, train=True, generator=torch.Generator().manual_seed(0))
    z = o[0, 2] - 0.5 * (e[0, 1:] + e[0, :-1])
    in_person, in_ground = ((z > 0.75) & (z < 2.25)).sum(), (z < 0.25).sum()
    assert in_person >= 8 and in_ground >= 4, z
    assert ((z > 2.5) & (z < 4.5)).sum() <= 3  # the empty air above gets the small empty share only
    assert (e[0, 1:] >= e[0, :-1]).all() and torch.isfinite(e).all()


def test_occupancy_full_refresh_replaces_and_partial_refresh_keeps_the_maximum():
    s = OccupancySampler((4, 4, 4), update_fraction=0.25, decay=0.5)
    s.update(lambda p: torch.full((p.shape[0],), 8.0), LO, HI, full=True)
    assert torch.equal(s.grid, torch.full((4, 4, 4), 8.0))  # the fresh grid's 'all occupied' is gone
    s.update(lambda p: torch.zeros(p.shape[0]), LO, HI)
    assert (s.grid == 4.0).sum() == 16 and (s.grid == 8.0).sum() == 48  # a quarter decayed once
    assert s.occupied(LO, HI).all()
    s.update(lambda p: torch.zeros(p.shape[0]), LO, HI, full=True)
    assert not s.occupied(LO, HI).any()
    o, d = torch.tensor([[0.0, 0.0, 15.0]]), torch.tensor([[0.0, 0.0, -1.0]])
    e = s.edges(o, d, LO, HI, train=False)  # nothing occupied: the empty share alone, i.e. stratified
    assert torch.allclose(e, StratifiedSampler(32).edges(o, d, LO, HI, train=False), atol=1e-3)


def test_the_first_refresh_of_a_fresh_occupancy_grid_reads_every_cell():
    s = OccupancySampler((4, 4, 4), update_fraction=0.25)
    s.update(lambda p: torch.zeros(p.shape[0]), LO, HI)  # asked for a quarter, gets all: nothing stays "fresh"
    assert not s.occupied(LO, HI).any()
    s.update(lambda p: torch.full((p.shape[0],), 8.0), LO, HI)  # now a quarter only
    assert (s.grid == 8.0).sum() == 16


def test_occupancy_edges_of_rays_that_miss_graze_or_start_inside_the_box():
    s = OccupancySampler((8, 8, 11), n_samples=16, n_coarse=64, update_fraction=1.0)
    s.update(lambda p: (p[:, 2] < 0.0).float() * 1e9, LO, HI, full=True)  # huge density in the floor cell only
    o = torch.tensor([[100.0, 0.0, 15.0], [-60.0, 0.0, 50.0], [0.0, 0.0, 2.0], [0.0, 0.0, 5.0]])
    d = torch.nn.functional.normalize(torch.tensor([[0.0, 0.0, -1.0], [1.0, 0.0, -0.8], [0.0, 0.0, -1.0],
                                                    [1.0, 0.0, 0.0]]), dim=-1)  # miss, grazing 50 m, inside, on top
    for train in (False, True):
        e = s.edges(o, d, LO, HI, train=train, generator=torch.Generator().manual_seed(1))
        near, far, hit = ray_box(o, d, LO, HI)
        assert torch.isfinite(e).all() and (e[:, 1:] >= e[:, :-1]).all()
        assert torch.allclose(e[:, 0], near) and torch.allclose(e[:, -1], far)
        assert (e[~hit, -1] - e[~hit, 0] == 0).all()  # a miss keeps zero-length intervals


def test_background_below_and_above_horizon():
    bg = Background(0.0, 30.0, resolution=8)
    o = torch.tensor([[0.0, 0.0, 50.0]] * 3)
    d = torch.tensor([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 0.6, 0.8]])
    out = bg(o, d)
    assert out.shape == (3, 3) and torch.isfinite(out).all()


def test_render_rays_missing_slab_gives_background_and_background_mask():
    cfg = FieldConfig(aabb_lo=tuple(LO.tolist()), aabb_hi=tuple(HI.tolist()), resolutions=[(4, 4, 2)],
                      log2_table=8, n_images=2)
    m = StaticModel(cfg, SamplerConfig("stratified", 8), 0.0, 20.0)
    o = torch.tensor([[100.0, 0.0, 15.0]])
    d = torch.tensor([[0.0, 0.0, 1.0]])
    res = m.render_rays(o, d, torch.tensor([1]))
    assert res["acc"].item() == 0
    assert torch.allclose(res["rgb"], m.background(o, d))
    assert torch.allclose(res["mask_probs"], torch.tensor([[1.0, 0, 0, 0]]))


def test_view_dependent_field_needs_dirs():
    cfg = FieldConfig(resolutions=[(4, 4, 4)], log2_table=8, view_dependent=True)
    f = StaticField(cfg)
    pts = torch.zeros(5, 3)
    out = f(pts, torch.nn.functional.normalize(torch.randn(5, 3), dim=-1))
    assert out["rgb"].shape == (5, 3) and out["mask_logits"].shape == (5, 4)
    try:
        f(pts)
    except ValueError as exc:
        assert "view dependent" in str(exc)
    else:
        raise AssertionError("expected ValueError")


def test_gradients_finite_after_100_steps_on_random_data():
    torch.manual_seed(0)
    for enc in ("hash", "planes"):
        cfg = FieldConfig(aabb_lo=tuple(LO.tolist()), aabb_hi=tuple(HI.tolist()), encoding=enc,
                          resolutions=[(4, 4, 2), (16, 16, 8)], features=2 if enc == "hash" else 4,
                          log2_table=8, n_images=4)
        m = StaticModel(cfg, SamplerConfig("stratified", 16), 0.0, 20.0)
        opt = torch.optim.Adam(m.parameters(), lr=1e-2)
        for _ in range(100):
            o = torch.randn(64, 3) * 5 + torch.tensor([0, 0, 20.0])
            d = torch.nn.functional.normalize(torch.randn(64, 3) * 0.3 + torch.tensor([0, 0, -1.0]), dim=-1)
            res = m.render_rays(o, d, torch.randint(4, (64,)), train=True)
            loss = (res["rgb"] - torch.rand(64, 3)).square().mean() + 1e-2 * m.distortion(res)
            loss = loss - torch.log(res["mask_probs"].clamp_min(1e-6))[:, 0].mean() * 0.1
            opt.zero_grad()
            loss.backward()
            for p in m.parameters():
                assert p.grad is None or torch.isfinite(p.grad).all()
            opt.step()
        assert np.isfinite(float(loss.detach()))


@pytest.mark.parametrize("tilt", [0.0, 30.0, 89.0])
def test_topdown_rays_start_above_the_box_and_look_down_within_the_tilt(tilt):
    o, d = topdown_rays(LO, HI, 500, tilt, torch.Generator().manual_seed(0))
    assert torch.allclose(o[:, 2], HI[2] + 1.0)
    assert ((o[:, :2] >= LO[:2]) & (o[:, :2] <= HI[:2])).all()
    assert torch.allclose(d.norm(dim=-1), torch.ones(500))
    off_nadir = torch.rad2deg(torch.acos((-d[:, 2]).clamp(-1, 1)))
    assert float(off_nadir.max()) <= tilt + 1e-3 and (d[:, 2] < 0).all()


def test_topdown_distortion_penalises_density_floating_over_the_ground():
    """Seen from above, an opaque ground alone has low distortion; a faint layer 3 m above it splits
    each ray's weight in two and costs more; the loss's gradient is finite on a real field."""
    cfg = FieldConfig(aabb_lo=tuple(LO.tolist()), aabb_hi=tuple(HI.tolist()), resolutions=[(4, 4, 2), (8, 8, 4)],
                      log2_table=8)
    m = StaticModel(cfg, SamplerConfig("stratified", 64), 0.0, 20.0)
    o, d = topdown_rays(LO, HI, 256, 0.0, torch.Generator().manual_seed(1))
    geo_dim = m.field.geometry(o[:2])[1].shape[1]

    def with_density(floater: float):
        def geometry(p):
            sigma = 50.0 * (p[:, 2].abs() < 0.1) + floater * ((p[:, 2] - 3.0).abs() < 0.5)
            return sigma.float(), torch.zeros(len(p), geo_dim)
        return geometry

    losses = {}
    for floater in (0.0, 1.0):
        m.field.geometry = with_density(floater)
        losses[floater] = float(m.geometry_distortion(o, d))
    del m.field.geometry  # the field's own again
    assert losses[1.0] > 5 * losses[0.0]
    loss = m.geometry_distortion(o, d)
    loss.backward()
    assert torch.isfinite(loss)
    assert all(p.grad is None or torch.isfinite(p.grad).all() for p in m.parameters())


def test_rays_through_the_slab_floor_end_opaque():
    cfg = FieldConfig(aabb_lo=tuple(LO.tolist()), aabb_hi=tuple(HI.tolist()), resolutions=[(4, 4, 2)],
                      log2_table=8, density_bias=-30.0)  # an empty field
    m = StaticModel(cfg, SamplerConfig("stratified", 8), 0.0, 20.0)
    o = torch.tensor([[0.0, 0.0, 15.0], [-30.0, 0.0, 4.0]])
    d = torch.nn.functional.normalize(torch.tensor([[0.1, 0.0, -1.0], [1.0, 0.0, 0.0]]), dim=-1)
    res = m.render_rays(o, d)
    assert res["acc"][0].item() == pytest.approx(1.0)  # down through the floor: opaque
    assert res["acc"][1].item() < 1e-6  # out through a side: background
