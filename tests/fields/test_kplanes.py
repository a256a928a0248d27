"""K-Planes pieces on hand-computed values: gated gradients, L_cos, plane sampling, regularisers."""

import math

import pytest
import torch

from fields.kplanes import (
    STATIC_LOGIT,
    KPlanesConfig,
    KPlanesEncoding,
    KPlanesField,
    KPlanesFieldConfig,
    cosine_separation,
    gate_grad,
    sample_plane,
    sample_plane_reference,
)


def test_gate_grad_passes_values_and_masks_gradients():
    x = torch.tensor([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]], requires_grad=True)
    gate = torch.tensor([[1.0], [0.0], [0.5]])
    y = gate_grad(x, gate)
    assert torch.equal(y, x)
    (y * torch.tensor([[1.0, 10.0]])).sum().backward()
    assert x.grad.tolist() == [[1.0, 10.0], [0.0, 0.0], [0.5, 5.0]]


def test_gate_grad_blocks_through_a_longer_graph():
    w = torch.tensor(2.0, requires_grad=True)
    out = gate_grad(w * torch.ones(4), torch.tensor([0.0, 0.0, 1.0, 0.0])) ** 2
    out.sum().backward()
    assert w.grad.item() == pytest.approx(2 * 2.0)  # only element 2 counts: d(w^2)/dw = 2w


def test_cosine_separation_hand_values():
    a = [torch.tensor([[1.0, 0.0], [1.0, 1.0]])]
    b = [torch.tensor([[0.0, 1.0], [-1.0, -1.0]])]
    # cos = 0 for the first point, -1 for the second: mean |cos| = 0.5
    assert cosine_separation(a, b).item() == pytest.approx(0.5)
    two = cosine_separation(a * 2, [torch.tensor([[2.0, 0.0], [1.0, 0.0]])] * 2)
    assert two.item() == pytest.approx(2 * (1.0 + 1 / math.sqrt(2)) / 2)
    z = cosine_separation([torch.zeros(3, 4)], [torch.ones(3, 4)])  # zero vectors: finite, 0
    assert torch.isfinite(z) and z.item() == 0.0


def test_plane_sampling_matches_reference_including_bounds():
    torch.manual_seed(0)
    plane = torch.randn(1, 5, 7, 9)
    u = torch.cat([torch.rand(200), torch.tensor([0.0, 1.0, 1.0, 0.0])])
    v = torch.cat([torch.rand(200), torch.tensor([0.0, 1.0, 0.0, 1.0])])
    assert torch.allclose(sample_plane(plane, u, v), sample_plane_reference(plane, u, v), atol=1e-5)


def test_time_planes_start_at_one_so_a_fresh_field_is_static():
    enc = KPlanesEncoding(KPlanesConfig(base_resolution=(4, 4, 2), multipliers=(1, 2), time_resolution=5,
                                        features=3))
    x = torch.rand(50, 3)
    f0 = enc(x, torch.zeros(50))["features"]
    f1 = enc(x, torch.ones(50))["features"]
    assert torch.allclose(f0, f1)
    assert enc.time_l1().item() == 0.0 and enc.time_smoothness().item() == 0.0
    assert enc.out_dim == 6 == f0.shape[1]


def test_extended_encoding_shapes_and_mask_gating_reaches_only_one_plane_set():
    cfg = KPlanesConfig(base_resolution=(4, 4, 2), multipliers=(1,), time_resolution=4, features=3, extended=True)
    enc = KPlanesEncoding(cfg)
    x, t = torch.rand(20, 3), torch.rand(20)
    out = enc(x, t, dynamic_gate=torch.zeros(20))  # all static pixels
    assert out["features"].shape == (20, enc.out_dim) == (20, 2 * 3 + 3)
    out["features"].sum().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in enc.static_planes)
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in enc.dynamic_planes[:3])
    enc.zero_grad()
    out = enc(x, t, dynamic_gate=torch.ones(20))  # all dynamic pixels
    out["features"][:, :6].sum().backward()
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in enc.static_planes)
    assert all(p.grad.abs().sum() > 0 for p in enc.dynamic_planes[:3])
    assert len(out["static_space"]) == len(out["dynamic_space"]) == 3


def test_field_outputs_are_finite_and_gradients_survive_100_steps():
    torch.manual_seed(1)
    cfg = KPlanesFieldConfig(planes=KPlanesConfig(base_resolution=(6, 6, 3), multipliers=(1, 2), time_resolution=4,
                                                  features=4, extended=True), hidden=16, n_images=3)
    field = KPlanesField(cfg)
    opt = torch.optim.Adam(field.parameters(), lr=1e-2)
    for _ in range(100):
        pts = torch.rand(64, 3) * 2 - 1
        out = field(pts, torch.rand(64), image_idx=torch.randint(0, 3, (64,)), dynamic_gate=torch.rand(64))
        loss = ((out["rgb"] - torch.rand(64, 3)) ** 2).mean() + 1e-3 * out["sigma"].mean() \
            + 0.01 * cosine_separation(out["static_space"], out["dynamic_space"]) \
            + 0.01 * field.encoding.total_variation() + 0.01 * field.encoding.time_smoothness()
        opt.zero_grad()
        loss.backward()
        assert all(torch.isfinite(p.grad).all() for p in field.parameters() if p.grad is not None)
        opt.step()
    assert torch.isfinite(out["sigma"]).all() and (out["dynamic_prob"] >= 0).all()
    assert KPlanesFieldConfig.from_json(cfg.to_json()) == cfg


@pytest.mark.parametrize("extended", [False, True])
def test_density_alone_equals_the_full_forward_density(extended):
    torch.manual_seed(2)
    cfg = KPlanesFieldConfig(planes=KPlanesConfig(base_resolution=(6, 6, 3), multipliers=(1, 2), time_resolution=4,
                                                  features=4, extended=extended), hidden=16, n_images=2)
    field = KPlanesField(cfg)
    for p in field.encoding.time_planes():  # time planes away from 1, so times matter
        torch.nn.init.uniform_(p, 0.5, 1.5)
    pts = torch.rand(50, 3) * 2.4 - 1.2  # some outside the box: density 0 there
    times = torch.rand(50)
    sigma = field.density(pts, times)
    assert torch.equal(sigma, field(pts, times, with_mask=False)["sigma"])
    assert (sigma[(pts.abs() > 1).any(dim=-1)] == 0).all()


def test_time_gate_hand_values_static_where_the_mask_says_nobody_is():
    """``f_d = S_d * (1 + p * (T_d - 1))``: at p = 0 the time planes drop out, at p = 1 it is the stock
    product, in between linear; the mask channel (the source of p) gets no gradient through it."""
    cfg = KPlanesConfig(base_resolution=(2, 2, 2), multipliers=(1,), time_resolution=2, features=1, extended=True,
                        time_gate=True)
    enc = KPlanesEncoding(cfg)
    with torch.no_grad():
        for k, p in enumerate(enc.dynamic_planes[:3]):
            p.fill_(2.0 + k)  # S_d = 2 * 3 * 4 = 24
        for p in enc.dynamic_planes[3:]:
            p[:, :1] = 0.5  # T_d = 0.125
    x, t = torch.full((3, 3), 0.5), torch.full((3,), 0.5)
    for logit, p_dyn in ((-1e4, 0.0), (1e4, 1.0), (0.0, 0.5)):
        with torch.no_grad():
            for p in enc.dynamic_planes[3:]:
                p[:, 1:] = logit
        f_d = enc(x, t)["features"][:, 1]
        assert torch.allclose(f_d, torch.full((3,), 24.0 * (1 + p_dyn * (0.125 - 1.0))))
    enc(x, t)["features"][:, 1].sum().backward()  # at p = 1/2
    assert all(p.grad[:, 1:].abs().sum() == 0 for p in enc.dynamic_planes[3:])  # mask channel: no gradient
    assert all(p.grad[:, :1].abs().sum() > 0 for p in enc.dynamic_planes[3:])  # time features: p x the stock one


@pytest.mark.parametrize("z_top", [1.0, 0.45])
@pytest.mark.parametrize("time_gate", [False, True])
@pytest.mark.parametrize("pattern,space_points", [("mixed", 24), ("mixed", None), ("mixed", 0), ("static", 24),
                                                  ("dynamic", 24), ("mixed", 1000), ("runs", 24), ("runs", 0)])
def test_split_sampling_under_a_hard_gate_equals_gating(pattern, space_points, time_gate, z_top):
    """The fast path (planes sampled with autograd only where the gate lets gradients through) gives the
    values and the gradients of planes and coordinates that gating every sample gives, whether the points
    come in any order ("mixed": permuted and back) or already in its runs ("runs": the space points,
    then static, then dynamic ones, as the trainer orders its rays with ``gate_ray_runs``; used in place)."""
    torch.manual_seed(3)
    cfg = KPlanesConfig(base_resolution=(5, 4, 3), multipliers=(1, 2), time_resolution=6, features=3, extended=True,
                        time_gate=time_gate, dynamic_z_top=z_top)
    enc = KPlanesEncoding(cfg)
    with torch.no_grad():
        for p in enc.dynamic_planes:  # time planes away from their initial 1 / 0, so every gradient is non-trivial
            p.add_(0.3 * torch.randn_like(p))
    n = 96
    x0, t = torch.rand(n, 3), torch.rand(n)
    mixed = (torch.rand(n) < 0.3).float()
    runs = torch.cat([mixed[:24], torch.zeros(50), torch.ones(n - 74)])
    gate = {"mixed": mixed, "runs": runs, "static": torch.zeros(n), "dynamic": torch.ones(n)}[pattern]
    w_feat, w_mask = torch.randn(n, enc.out_dim), torch.randn(n, 3 * 2)

    def run(split: bool):
        enc.split_hard_gate = split
        enc.zero_grad()
        x = x0.clone().requires_grad_(True)
        out = enc(x, t, dynamic_gate=gate, space_points=space_points)
        loss = (out["features"] * w_feat).sum() + (out["mask_values"] * w_mask).sum()
        if out["static_space"] and out["static_space"][0].shape[0]:
            loss = loss + cosine_separation(out["static_space"], out["dynamic_space"])
        loss.backward()
        grads = [p.grad.clone() if p.grad is not None else torch.zeros_like(p) for p in enc.parameters()]
        return out, grads, x.grad.clone()

    ref, ref_grads, ref_x = run(False)
    fast, fast_grads, fast_x = run(True)
    enc.split_hard_gate = True
    assert torch.equal(fast["features"], ref["features"]) and torch.equal(fast["mask_values"], ref["mask_values"])
    for a, b in zip(fast["static_space"] + fast["dynamic_space"], ref["static_space"] + ref["dynamic_space"],
                    strict=True):
        assert torch.equal(a, b)
    for a, b in zip(fast_grads, ref_grads, strict=True):
        assert torch.allclose(a, b, atol=1e-5, rtol=1e-4)
    assert torch.allclose(fast_x, ref_x, atol=1e-5, rtol=1e-4)
    assert any(g.abs().sum() > 0 for g in ref_grads)


@pytest.mark.parametrize("time_gate", [False, True])
def test_above_the_dynamic_layer_a_point_is_static(time_gate):
    """With ``dynamic_z_top`` 0.4 the dynamic planes have 40 % of the z grid points; a point above the layer
    has f_d = 0, "static" mask values and the same features at every time, and sends no gradient to the
    dynamic planes; below it the planes read z stretched over the layer."""
    torch.manual_seed(0)
    cfg = KPlanesConfig(base_resolution=(4, 4, 10), multipliers=(1, 2), time_resolution=5, features=2,
                        extended=True, time_gate=time_gate, dynamic_z_top=0.4)
    enc = KPlanesEncoding(cfg)
    assert [tuple(p.shape[2:]) for p in enc.dynamic_planes[:6]] == [(4, 4), (4, 4), (4, 4), (5, 4), (5, 4), (5, 4)]
    assert enc.static_planes[1].shape[2:] == (10, 4)  # xz: z rows, the whole box
    with torch.no_grad():
        for p in enc.dynamic_planes:
            p.add_(0.3 * torch.randn_like(p))
    high = torch.tensor([[0.3, 0.6, 0.41], [0.9, 0.1, 1.0]])
    per_t = [enc(high, torch.full((2,), t)) for t in (0.0, 0.37, 1.0)]
    for out in per_t:
        f = out["features"]
        assert torch.equal(f, per_t[0]["features"])
        assert torch.equal(f[:, 2:4], torch.zeros(2, 2)) and torch.equal(f[:, 6:8], torch.zeros(2, 2))  # f_d
        assert torch.equal(f[:, 8:], torch.zeros(2, 6))  # mask inputs of the fusion
        assert torch.equal(out["mask_values"], torch.full((2, 6), STATIC_LOGIT))
    for gate, space_points in ((torch.ones(2), None), (torch.tensor([0.0, 1.0]), 0)):  # the latter reads no plane
        enc.zero_grad()
        out = enc(high, torch.rand(2), dynamic_gate=gate, space_points=space_points)
        assert torch.equal(out["features"], per_t[0]["features"])
        (out["features"].sum() + out["mask_values"].sum()).backward()
        assert all(p.grad is None or p.grad.abs().sum() == 0 for p in enc.dynamic_planes)
    # below the layer: the stretched z reads the dynamic planes as a box of 40 % the height would
    low = torch.tensor([[0.3, 0.6, 0.2]])
    plain = KPlanesEncoding(KPlanesConfig(base_resolution=(4, 4, 4), multipliers=(1, 2), time_resolution=5,
                                          features=2, extended=True, time_gate=time_gate))
    with torch.no_grad():
        for a, b in zip(plain.dynamic_planes, enc.dynamic_planes, strict=True):
            a.copy_(b)
    t = torch.tensor([0.6])
    dyn_cols = torch.tensor([2, 3, 6, 7, 8, 9, 10, 11, 12, 13])  # f_d of both scales, the mask inputs
    got = enc(low, t)["features"][:, dyn_cols]
    want = plain(torch.tensor([[0.3, 0.6, 0.5]]), t)["features"][:, dyn_cols]
    assert torch.allclose(got, want, atol=1e-6)


def test_dynamic_layer_top_from_the_ground_and_a_height():
    from fields.dynamic_training import dynamic_layer_top
    from fields.scene import SceneBounds

    b = SceneBounds(lo=(0.0, 0.0, -0.5), hi=(10.0, 10.0, 5.5), ground_z=0.0, source="test", finest_gsd_m=0.1,
                    median_gsd_m=0.1)
    assert dynamic_layer_top(b, None)[0] == 1.0
    top, why = dynamic_layer_top(b, 2.5)
    assert top == pytest.approx(0.5) and "3.00 m of the 6.00 m box" in why
    assert dynamic_layer_top(b, 8.0)[0] == 1.0
    with pytest.raises(ValueError):
        dynamic_layer_top(b, float("nan"))
    with pytest.raises(ValueError):
        KPlanesEncoding(KPlanesConfig(extended=True, dynamic_z_top=0.0))
    stock = KPlanesConfig(base_resolution=(2, 2, 8), dynamic_z_top=0.5)  # stock: one set of planes, whole box
    assert stock.dynamic_resolutions() == stock.resolutions()


def test_soft_gates_and_inference_take_the_gated_path():
    cfg = KPlanesConfig(base_resolution=(4, 4, 2), multipliers=(1,), time_resolution=4, features=3, extended=True)
    enc = KPlanesEncoding(cfg)
    x, t = torch.rand(10, 3), torch.rand(10)
    soft = enc(x, t, dynamic_gate=torch.full((10,), 0.5))
    with torch.no_grad():
        inference = enc(x, t, dynamic_gate=torch.ones(10))
    assert torch.allclose(soft["features"], inference["features"])
    assert soft["static_space"][0].shape == (10, 3)


def test_coarse_to_fine_weights_hand_values():
    from fields.kplanes import coarse_to_fine_weights

    assert torch.equal(coarse_to_fine_weights(3, 0.0, 0.0), torch.ones(3))  # off
    assert torch.allclose(coarse_to_fine_weights(3, 0.0, 0.4), torch.tensor([1.0, 0.0, 0.0]))
    # b = 2 * 0.1 / 0.4 = 0.5: scale 1 half way up the cosine ramp, scale 2 not started
    assert torch.allclose(coarse_to_fine_weights(3, 0.1, 0.4), torch.tensor([1.0, 0.5, 0.0]), atol=1e-6)
    assert torch.allclose(coarse_to_fine_weights(3, 0.3, 0.4), torch.tensor([1.0, 1.0, 0.5]), atol=1e-6)
    assert torch.equal(coarse_to_fine_weights(3, 0.4, 0.4), torch.ones(3))
    assert torch.equal(coarse_to_fine_weights(3, 1.5, 0.4), torch.ones(3))  # progress past the end


@pytest.mark.parametrize("extended", [False, True])
def test_a_faded_out_scale_gives_zero_features_and_no_gradient_to_its_planes(extended):
    torch.manual_seed(0)
    enc = KPlanesEncoding(KPlanesConfig(base_resolution=(4, 4, 2), multipliers=(1, 2), time_resolution=3,
                                        features=4, extended=extended))
    x, t = torch.rand(50, 3), torch.rand(50)
    full = enc(x, t)["features"].detach()
    enc.set_scale_weights(torch.tensor([1.0, 0.0]))
    out = enc(x, t)["features"]
    per_scale = 4 * (2 if extended else 1)
    assert torch.equal(out[:, :per_scale], full[:, :per_scale])
    assert (out[:, per_scale:2 * per_scale] == 0).all()
    assert torch.equal(out[:, 2 * per_scale:], full[:, 2 * per_scale:])  # mask channels untouched
    out[:, :2 * per_scale].sum().backward()
    fine = enc.dynamic_planes[6:9] if not extended else list(enc.static_planes[3:]) + list(enc.dynamic_planes[6:9])
    assert all(p.grad is None or (p.grad == 0).all() for p in fine)
    assert enc.dynamic_planes[0].grad is not None and enc.dynamic_planes[0].grad.abs().sum() > 0
