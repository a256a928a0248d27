"""The mask-only phase: live samples of cached rays on a frozen geometry, composited sparsely."""

import torch

from fields.data import load_flight
from fields.rendering import composite
from fields.training import FitConfig, fit
from tests.fields.test_render_shortcuts import _thin_ground_model


def test_sparse_mask_composite_equals_the_dense_one():
    m = _thin_ground_model([])
    torch.manual_seed(1)
    r, s = 6, 5
    w = torch.rand(r, s) * 0.3
    w[0] = 0.0  # a ray that sees nothing: all background
    w[1, 2] = 1e-6  # below min_weight: not evaluated
    pts, geo = torch.randn(r * s, 3), torch.randn(r * s, 15)
    dense = torch.softmax(m.field.mask_logits(pts, geo), -1).view(r, s, -1)
    dense = dense * (w >= m.sampler_config.min_weight)[..., None]
    bg = torch.zeros(dense.shape[-1])
    bg[0] = 1.0
    expected = composite(w, dense, bg)
    got = m._mask_probs(w, pts, geo)
    assert torch.allclose(got, expected, atol=1e-6)
    assert torch.allclose(got[0], bg) and torch.allclose(got.sum(-1), torch.ones(r), atol=1e-5)


def test_mask_phase_trains_only_the_mask(tiny_flight):
    d = load_flight(tiny_flight)
    cfg = FitConfig(iters=30, budget_s=None, batch_rays=256, n_samples=16, budget_mb=1.0, threads=1,
                    log_every_s=0.0, mask_phase_share=0.5, mask_phase_rays=600, mask_phase_batch_rays=200)
    snap = {}

    def at_end_of_rgb_phase(model, step, train_s):
        snap.update({k: v.clone() for k, v in model.state_dict().items()})
        snap["step"] = step

    res = fit(d, cfg, on_eval=at_end_of_rgb_phase, eval_at_iters=[15])
    assert snap["step"] == 15 and res.step == 30 and res.mask_steps == 15
    after = res.model.state_dict()
    mask_keys = [k for k in after if k.startswith(("field.mask_grid", "field.mask_head"))]
    assert mask_keys and any(not torch.equal(after[k], snap[k]) for k in mask_keys)
    assert all(torch.equal(after[k], snap[k]) for k in after if k not in mask_keys)
    assert "mask_nll" in res.curve[-1] and "train_psnr" in res.curve[0]


def test_mask_phase_without_labels_is_skipped(tiny_flight, tmp_path):
    import shutil

    flight = tmp_path / "f"
    shutil.copytree(tiny_flight, flight)
    shutil.rmtree(flight / "labels")
    d = load_flight(flight)
    res = fit(d, FitConfig(iters=10, budget_s=None, batch_rays=128, n_samples=8, budget_mb=1.0, threads=1,
                           log_every_s=1e9, mask_phase_share=0.5))
    assert res.step == 10 and res.mask_steps == 0


def test_a_fresh_mask_can_start_as_background_everywhere():
    """With ``mask_init_background`` untrained places are not blobs: the default (~uniform, 1/4
    background) makes every place that no mask ray reached foreground, i.e. boxes all over a view."""
    from fields.field import FieldConfig, StaticField
    from fields.mask_boxes import boxes_from_probabilities

    f = StaticField(FieldConfig(n_classes=3, mask_init_background=0.99))
    probs = torch.softmax(f.mask_logits(torch.rand(500, 3) * 2 - 1, torch.randn(500, 15)), -1)
    assert probs[:, 0].min() > 0.98
    assert torch.allclose(probs[:, 1], probs[:, 2], atol=5e-3)  # no class preferred
    old = StaticField(FieldConfig(n_classes=3))  # torch's default init: ~uniform
    p_old = torch.softmax(old.mask_logits(torch.rand(64, 3), torch.randn(64, 15)), -1)
    assert boxes_from_probabilities(p_old.detach().view(8, 8, 4).numpy())  # the old start: one big blob
    assert not boxes_from_probabilities(probs[:64].detach().view(8, 8, 4).numpy())


def test_cached_rays_composite_like_the_renderer():
    from fields.data import RayBank
    from fields.training import _MaskCache
    from telemetry.camera import Camera, Mount
    from telemetry.frames import orbit_pose

    m = _thin_ground_model([])
    cam = Camera.from_fov(16, 12, 60.0, Mount(pitch_deg=-60))
    bank = RayBank(cam, [orbit_pose(8.0, 4.0, -60.0, 30.0)])
    fi, pi = torch.zeros(100, dtype=torch.long), torch.randperm(bank.hw)[:100]
    masks = torch.randint(0, 4, (1, bank.hw))
    cache = _MaskCache(m, bank, fi, pi, masks, torch.ones(2), torch.ones(4))
    rays = torch.tensor([5, 0, 99, 42, 5])
    o, d = bank.rays(fi[rays], pi[rays])
    with torch.no_grad():
        expected = m.render_rays(o, d, None, train=False)["mask_probs"]
        assert torch.allclose(cache.probs(m, rays), expected, atol=1e-5)
    assert torch.isfinite(cache.loss(m, 64, torch.Generator().manual_seed(0)))


def test_box_pixels_that_see_the_ground_are_taught_as_background():
    """Two samples per ray, at 1.2 m and 0.02 m: a box pixel with >= 10 % of its weight up high keeps
    its class (a person, or a pixel half on a head), one with less becomes background; non-box pixels
    and non-finite weights are untouched; a raised ground (z = 5 m) makes every sample ground."""
    from fields.training import ground_in_box_as_background

    z = torch.tensor([[1.2, 0.02]] * 5)
    w = torch.tensor([[0.0, 1.0], [0.9, 0.1], [0.5, 0.5], [float("nan"), 0.5], [0.05, 0.9]])
    target = torch.tensor([2, 1, 3, 1, 2])
    assert ground_in_box_as_background(target, w, z, 0.0, 0.1).tolist() == [0, 1, 3, 1, 0]
    assert ground_in_box_as_background(torch.zeros(5, dtype=torch.long), w, z, 0.0, 0.1).tolist() == [0] * 5
    assert ground_in_box_as_background(target, w, z, 5.0, 0.1).tolist() == [0, 0, 0, 1, 0]


def test_fit_with_the_ground_cut_keeps_finite_weights(tiny_flight):
    data = load_flight(tiny_flight)
    cfg = FitConfig(iters=4, budget_s=None, n_samples=8, batch_rays=256, budget_mb=1.0, threads=1,
                    mask_box_min_height_m=0.1, mask_pos_fraction=0.25)
    res = fit(data, cfg)
    assert all(torch.isfinite(p).all() for p in res.model.parameters())
