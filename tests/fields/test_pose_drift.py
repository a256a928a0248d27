"""Time-smooth pose corrections (fields.pose_drift): rotation maths, knot interpolation, pose/ray
agreement, recovery of a known drift, and the dynamic fitter with corrections on."""


import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from fields.pose_drift import PoseDrift, knot_count, rotate, warmup_scale
from telemetry.frames import look_at

rotvecs = st.lists(st.floats(-3.0, 3.0, allow_nan=False), min_size=3, max_size=3)


@settings(max_examples=60, deadline=None)
@given(rotvecs)
def test_rotate_matches_scipy(w):
    v = torch.tensor([[0.3, -1.2, 2.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    got = rotate(torch.tensor(w, dtype=torch.float64), v).numpy()
    want = Rotation.from_rotvec(w).apply(v.numpy())
    assert np.allclose(got, want, atol=1e-9)


def test_rotate_at_zero_and_tiny_angles_has_finite_gradients():
    for scale in (0.0, 1e-12, 1e-5, 1e-3):
        w = torch.full((1, 3), scale, dtype=torch.float64, requires_grad=True)
        out = rotate(w, torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64))
        out.sum().backward()
        assert torch.isfinite(w.grad).all()
        want = Rotation.from_rotvec(w.detach().numpy()[0]).apply([0.0, 0.0, -1.0])
        assert np.allclose(out.detach().numpy()[0], want, atol=1e-12)
    # d/dw of w x v at w = 0 is -[v]x: the derivative of rotating (0, 0, -1) about x is (0, 1, 0)
    w = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    rotate(w, torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64))[1].backward()
    assert w.grad.tolist() == pytest.approx([1.0, 0.0, 0.0])


def test_knots_interpolate_linearly_and_clamp_outside_the_flight():
    drift = PoseDrift(3)
    with torch.no_grad():
        drift.trans.copy_(torch.tensor([[0.0, 0, 0], [1.0, 2, 3], [3.0, 2, 1]]))
    _, t = drift.at(torch.tensor([0.0, 0.25, 0.5, 1.0, -4.0, 7.0]))
    assert np.allclose(t.detach().numpy(), [[0, 0, 0], [0.5, 1, 1.5], [1, 2, 3], [3, 2, 1], [0, 0, 0], [3, 2, 1]])


def test_zero_knots_leave_rays_and_poses_unchanged():
    drift = PoseDrift(4)
    o, d = torch.randn(5, 3), torch.nn.functional.normalize(torch.randn(5, 3), dim=-1)
    o2, d2 = drift.apply(o, d, torch.rand(5))
    assert torch.equal(o2, o) and torch.allclose(d2, d)
    T = look_at(np.array([1.0, 2.0, 15.0]), np.array([5.0, 0.0, 0.0]))
    assert np.allclose(drift.correct_cam_from_world(T, 0.4), T, atol=1e-6)


def test_corrected_pose_casts_the_corrected_rays():
    """Rays of the corrected cam_from_world = the telemetry rays corrected by apply()."""
    from telemetry.camera import Camera

    cam = Camera.from_fov(16, 12, 70.0)
    T = look_at(np.array([-3.0, 1.0, 15.0]), np.array([4.0, 0.5, 0.0]))
    drift = PoseDrift(3)
    with torch.no_grad():
        drift.rot.copy_(torch.tensor([[0.01, -0.02, 0.03], [0.004, 0.0, -0.01], [0.0, 0.02, 0.0]]))
        drift.trans.copy_(torch.tensor([[0.5, -0.2, 0.8], [0.1, 0.3, -0.4], [0.0, 0.0, 0.2]]))
    uv = cam.pixel_grid().reshape(-1, 2)
    o, d = cam.rays_world(T, uv)
    o = torch.from_numpy(np.broadcast_to(o, d.shape).copy()).float()
    o2, d2 = drift.apply(o, torch.from_numpy(d).float(), torch.full((len(d),), 0.3))
    oc, dc = cam.rays_world(drift.correct_cam_from_world(T, 0.3), uv)
    assert np.allclose(o2.detach().numpy(), np.broadcast_to(oc, dc.shape), atol=1e-5)
    assert np.allclose(d2.detach().numpy(), dc, atol=1e-5)


def test_knot_count_from_flight_span_and_bad_values():
    assert knot_count(60.0, 1.0) == 61 and knot_count(0.0, 1.0) == 2 and knot_count(15.8, 2.0) == 9
    for span, spacing in ((float("nan"), 1.0), (-1.0, 1.0), (10.0, 0.0), (10.0, float("inf"))):
        with pytest.raises(ValueError):
            knot_count(span, spacing)
    with pytest.raises(ValueError, match="at least 2 knots"):
        PoseDrift(1)


def test_coarse_levels_add_their_interpolated_corrections():
    """Levels sum: fine 5 knots + coarse 3 knots at hand values, and the same correction held by the
    fine knots alone (the coarse knots nest in the fine ones) gives the same rays, penalty and summary."""
    both = PoseDrift(5, coarse_knots=[3])
    with torch.no_grad():
        both.trans[:, 0] = torch.tensor([0.0, 0.1, 0.0, 0.0, 0.2])
        both.coarse_trans[0][:, 0] = torch.tensor([1.0, 3.0, 2.0])
        both.coarse_rot[0][:, 2] = torch.tensor([0.0, 0.02, 0.01])
    rot, t = both.at(torch.tensor([0.0, 0.25, 0.5, 0.875, 1.0]))
    assert np.allclose(t[:, 0].detach().numpy(), [1.0, 2.0 + 0.1, 3.0, 2.25 + 0.1, 2.0 + 0.2])
    assert np.allclose(rot[:, 2].detach().numpy(), [0.0, 0.01, 0.02, 0.0125, 0.01])
    fine = PoseDrift(5)
    with torch.no_grad():
        fine.trans[:, 0] = torch.tensor([1.0, 2.1, 3.0, 2.5, 2.2])
        fine.rot[:, 2] = torch.tensor([0.0, 0.01, 0.02, 0.015, 0.01])
    t01 = torch.rand(50, generator=torch.Generator().manual_seed(3))
    o, d = torch.randn(50, 3), torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
    for a, b in zip(both.apply(o, d, t01), fine.apply(o, d, t01), strict=True):
        assert torch.allclose(a, b, atol=1e-6)
    assert float(both.penalty().detach()) == pytest.approx(float(fine.penalty().detach()), rel=1e-6)
    sb, sf = both.summary(), fine.summary()
    assert sb.pop("coarse_knots") == [3] and sf.pop("coarse_knots") == []
    assert sb == pytest.approx(sf, rel=1e-6)
    T = look_at(np.array([1.0, 2.0, 15.0]), np.array([5.0, 0.0, 0.0]))
    assert np.allclose(both.correct_cam_from_world(T, 0.6), fine.correct_cam_from_world(T, 0.6), atol=1e-6)


def test_coarse_levels_state_round_trip_and_bad_levels():
    a = PoseDrift(6, coarse_knots=[3, 2])
    with torch.no_grad():
        for p in a.parameters():
            p.normal_()
    b = PoseDrift(6, coarse_knots=[3, 2])
    b.load_state_dict(a.state_dict())
    t = torch.linspace(0, 1, 11)
    assert all(torch.equal(x, y) for x, y in zip(a.at(t), b.at(t), strict=True))
    assert PoseDrift(4).coarse_knots == [] and len(list(PoseDrift(4).parameters())) == 2
    for bad in ([1], [2.5], [0]):
        with pytest.raises(ValueError, match="at least 2 knots"):
            PoseDrift(6, coarse_knots=bad)


def _misses(drift, centres, dirs, t01, points):
    """Perpendicular distance (m) of each point to its corrected ray."""
    o, d = drift.apply(centres, dirs, t01)
    v = points - o
    return (v - (v * d).sum(-1, keepdim=True) * d).norm(dim=-1)


def test_gradient_descent_recovers_a_smooth_drift_and_corrects_heldout_frames():
    """Drifted cameras see known ground points; fitting the knots on the even frames so each ray
    passes through its point also puts the odd (held-out) frames' rays on their points, by
    interpolation in time alone: miss distance 0.2-0.8 m -> a few cm. (Rotation and translation
    trade against each other over a flat ground — 0.1 deg ~ 3 cm at 15 m — so the test scores rays,
    not the knots one by one.)"""
    g = torch.Generator().manual_seed(0)
    n_frames, rays = 40, 64
    t01 = torch.linspace(0, 1, n_frames)
    true = PoseDrift(5)
    with torch.no_grad():  # slow drift: a ramp and a sine, metres and radians
        k = torch.linspace(0, 1, 5)[:, None]
        true.trans.copy_(torch.cat([0.6 * k, 0.3 * torch.sin(3 * k), -0.5 * k], 1))
        true.rot.copy_(torch.cat([0.004 * k, -0.003 * k, 0.005 * torch.sin(2 * k)], 1))
    centres = torch.stack([torch.linspace(-10, 10, n_frames), torch.zeros(n_frames), torch.full((n_frames,), 15.0)], 1)
    fi = torch.randint(n_frames, (n_frames * rays,), generator=g)
    points = torch.cat([torch.rand(len(fi), 2, generator=g) * 20 - 10, torch.rand(len(fi), 1, generator=g)], 1)
    with torch.no_grad():  # the true camera (telemetry + drift) sees each point along d_true
        rot, trans = true.at(t01[fi])
        d_true = torch.nn.functional.normalize(points - (centres[fi] + trans), dim=-1)
        d_telemetry = rotate(-rot, d_true)  # the same pixel's direction in the telemetry pose
    train, held = fi % 2 == 0, fi % 2 == 1
    fit = PoseDrift(5)
    before = _misses(fit, centres[fi], d_telemetry, t01[fi], points).detach()
    # separate step sizes for metres and radians (one lr for both lets the rotation oscillate)
    opt = torch.optim.Adam([{"params": [fit.trans], "lr": 1e-2}, {"params": [fit.rot], "lr": 2e-4}])
    decay = torch.optim.lr_scheduler.ExponentialLR(opt, 0.1 ** (1 / 1000))
    for _ in range(1000):
        loss = _misses(fit, centres[fi][train], d_telemetry[train], t01[fi][train], points[train]).square().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        decay.step()
    after = _misses(fit, centres[fi], d_telemetry, t01[fi], points).detach()
    assert float(before[held].median()) > 0.2
    assert float(after[held].median()) < 0.03 and float(after[held].max()) < 0.1
    assert float((fit.trans - true.trans).detach().abs().max()) < 0.15


def test_background_pose_grad_passes_values_and_only_background_gradients():
    """Box rays render through the corrected pose (same values) but move the knots not at all: the
    knots' gradient is exactly the gradient of the background rays alone."""
    from fields.dynamic_training import background_pose_grad

    g = torch.Generator().manual_seed(1)
    o = torch.randn(6, 3, generator=g, dtype=torch.float64)
    d = torch.nn.functional.normalize(torch.randn(6, 3, generator=g, dtype=torch.float64), dim=-1)
    t = torch.rand(6, generator=g, dtype=torch.float64)
    background = torch.tensor([True, False, True, True, False, False])
    weight = torch.randn(6, 3, generator=g, dtype=torch.float64)

    def knot_grads(select):
        drift = PoseDrift(3).double()
        with torch.no_grad():
            drift.trans.normal_(generator=g)
            drift.rot.normal_(0.0, 0.01, generator=g)
        o2, d2 = drift.apply(o, d, t)
        o3, d3 = select(o2, d2)
        ((o3 + 2 * d3) * weight).sum().backward()
        return o2.detach(), o3.detach(), drift.trans.grad.clone(), drift.rot.grad.clone()

    g.manual_seed(7)
    o_all, o_gated, gt, gr = knot_grads(lambda a, b: background_pose_grad(a, b, background))
    g.manual_seed(7)  # the same knots; the loss restricted to the background rays by hand
    *_, gt_bg, gr_bg = knot_grads(lambda a, b: (torch.where(background[:, None], a, 0 * a),
                                                 torch.where(background[:, None], b, 0 * b)))
    assert torch.equal(o_gated, o_all)
    assert torch.allclose(gt, gt_bg) and torch.allclose(gr, gr_bg)
    assert gt.abs().sum() > 0
    g.manual_seed(7)
    *_, gt_none, gr_none = knot_grads(lambda a, b: background_pose_grad(a, b, torch.zeros(6, dtype=torch.bool)))
    assert not gt_none.any() and not gr_none.any()


def test_warmup_scale_holds_then_ramps():
    assert [warmup_scale(p, 0.1) for p in (0.0, 0.05, 0.1, 0.15, 0.2, 0.7, 1.0)] == pytest.approx(
        [0.0, 0.0, 0.0, 0.5, 1.0, 1.0, 1.0])
    assert warmup_scale(0.0, 0.0) == 1.0 and warmup_scale(0.3, -1.0) == 1.0


@settings(max_examples=80, deadline=None)
@given(st.floats(0.0, 1.0), st.floats(0.0, 1.0), st.floats(0.0, 0.5))
def test_warmup_scale_is_a_monotone_factor(a, b, delay):
    lo, hi = sorted((a, b))
    assert 0.0 <= warmup_scale(lo, delay) <= warmup_scale(hi, delay) <= 1.0


def test_per_frame_rows_match_by_time_and_add_their_residual_to_the_knots():
    """A frame's row applies to its own rays and to its pose looked up by its time; another time (a
    held-out frame, a novel pose) gets the knots alone; ray and pose corrections agree. The row acts
    through its residual: minus what the 3 knots fit at the 5 frames' times."""
    from telemetry.camera import Camera

    times = [0.0, 0.3, 0.5, 0.7, 1.0]
    drift = PoseDrift(3, frame_t01=times)
    assert drift.frames == 5
    assert [drift.frame_row(t) for t in (0.0, 0.3 + 5e-7, 0.7, 0.31, 0.9)] == [0, 1, 3, None, None]
    with torch.no_grad():
        drift.trans[:] = torch.tensor([0.2, 0.0, 0.0])
        drift.frame_trans[1] = torch.tensor([0.0, 0.05, -0.03])
        drift.frame_rot[1] = torch.tensor([0.001, -0.002, 0.0015])
    # least squares of a spike at t = 0.3 by hat functions at 0, 0.5, 1 (numpy, as a hand check)
    B = np.array([[1, 0, 0], [0.4, 0.6, 0], [0, 1, 0], [0, 0.6, 0.4], [0, 0, 1]])
    spike = np.zeros((5, 3))
    spike[1] = [0.0, 0.05, -0.03]
    want = spike - B @ np.linalg.lstsq(B, spike, rcond=None)[0]
    row_trans = drift.frame_residual()[1].detach()
    assert np.allclose(row_trans.numpy(), want, atol=1e-6)
    assert abs(float(row_trans[1, 1])) > 0.02  # most of a spike is no knot's to take
    rot, trans = drift.at(torch.tensor([0.3, 0.3]), torch.tensor([1, 0]))
    assert np.allclose(trans.detach().numpy(), [[0.2, 0, 0] + want[1], [0.2, 0, 0] + want[0]], atol=1e-6)

    cam = Camera.from_fov(16, 12, 70.0)
    T = look_at(np.array([-3.0, 1.0, 15.0]), np.array([4.0, 0.5, 0.0]))
    uv = cam.pixel_grid().reshape(-1, 2)
    o, d = cam.rays_world(T, uv)
    o = torch.from_numpy(np.broadcast_to(o, d.shape).copy()).float()
    rows = torch.ones(len(d), dtype=torch.long)
    o2, d2 = drift.apply(o, torch.from_numpy(d).float(), torch.full((len(d),), 0.3), rows)
    oc, dc = cam.rays_world(drift.correct_cam_from_world(T, 0.3), uv)
    assert np.allclose(o2.detach().numpy(), np.broadcast_to(oc, dc.shape), atol=1e-5)
    assert np.allclose(d2.detach().numpy(), dc, atol=1e-5)
    knots_only = PoseDrift(3)
    knots_only.load_state_dict({"rot": drift.rot.detach(), "trans": drift.trans.detach()})
    assert np.allclose(drift.correct_cam_from_world(T, 0.31), knots_only.correct_cam_from_world(T, 0.31), atol=1e-9)
    s = drift.summary()
    assert s["frames"] == 5
    assert s["frame_trans_rms_m"] == pytest.approx(float(np.sqrt(np.mean(np.sum(want ** 2, axis=1)))), rel=1e-4)


def test_rows_that_the_knots_can_represent_do_nothing():
    """As many frames as knots, at the knots' times: every row pattern is a knot pattern, so the
    residual is zero; a ramp over many frames is also the knots' (linear interpolation)."""
    drift = PoseDrift(4, frame_t01=np.linspace(0, 1, 4))
    with torch.no_grad():
        drift.frame_trans.normal_()
    assert float(drift.frame_residual()[1].detach().abs().max()) < 1e-5
    ramp = PoseDrift(3, frame_t01=np.linspace(0, 1, 17))
    with torch.no_grad():
        ramp.frame_rot[:] = torch.linspace(0, 0.01, 17)[:, None]
    assert float(ramp.frame_residual()[0].detach().abs().max()) < 1e-7


def test_without_per_frame_rows_the_state_is_a_knots_only_drift():
    """Checkpoints from before per-frame rows load unchanged: no new keys, rows off."""
    assert set(PoseDrift(4, coarse_knots=[2]).state_dict()) == {"rot", "trans", "coarse_rot.0", "coarse_trans.0"}
    assert PoseDrift(4).frames == 0 and PoseDrift(4).frame_row(0.5) is None
    assert set(PoseDrift(2, frame_t01=[0.0, 1.0]).state_dict()) == {"rot", "trans", "frame_t01", "frame_rot",
                                                                     "frame_trans"}
    with pytest.raises(ValueError, match="finite frame times"):
        PoseDrift(3, frame_t01=[0.0, float("nan")])


def test_per_frame_rows_learn_jitter_the_knots_cannot_and_spare_held_out_frames():
    """Smooth drift + white per-frame jitter (5 cm, ~0.15 deg): knots + rows fitted on the even
    frames (rows for those only) put the training rays on their points far better than knots alone,
    and the odd (held-out) frames, which have no row, score as well as with knots alone: the rows
    take only what the knots cannot, so the knots still learn the drift."""
    g = torch.Generator().manual_seed(2)
    n_frames, rays = 20, 32
    t01 = torch.linspace(0, 1, n_frames)
    truth = PoseDrift(4, frame_t01=t01.tolist())
    with torch.no_grad():
        k = torch.linspace(0, 1, 4)[:, None]
        truth.trans.copy_(torch.cat([0.4 * k, 0.2 * torch.sin(3 * k), -0.3 * k], 1))
    jitter_t = torch.randn(n_frames, 3, generator=g) * 0.05
    jitter_r = torch.randn(n_frames, 3, generator=g) * 0.0026 / 3 ** 0.5
    centres = torch.stack([torch.linspace(-10, 10, n_frames), torch.zeros(n_frames), torch.full((n_frames,), 15.0)], 1)
    fi = torch.randint(n_frames, (n_frames * rays,), generator=g)
    points = torch.cat([torch.rand(len(fi), 2, generator=g) * 20 - 10, torch.rand(len(fi), 1, generator=g)], 1)
    with torch.no_grad():
        rot, trans = truth.at(t01[fi])
        rot, trans = rot + jitter_r[fi], trans + jitter_t[fi]
        d_true = torch.nn.functional.normalize(points - (centres[fi] + trans), dim=-1)
        d_telemetry = rotate(-rot, d_true)
    train, held = fi % 2 == 0, fi % 2 == 1
    row_of = fi // 2  # the even frames' rows

    def fit(drift):
        rows = drift.frames > 0
        opt = torch.optim.Adam([{"params": [drift.trans, *([drift.frame_trans] if rows else [])], "lr": 1e-2},
                                {"params": [drift.rot, *([drift.frame_rot] if rows else [])], "lr": 2e-4}])
        decay = torch.optim.lr_scheduler.ExponentialLR(opt, 0.1 ** (1 / 400))
        for _ in range(400):
            o, d = drift.apply(centres[fi][train], d_telemetry[train], t01[fi][train],
                               row_of[train] if rows else None)
            v = points[train] - o
            loss = (v - (v * d).sum(-1, keepdim=True) * d).norm(dim=-1).square().mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            decay.step()
        with torch.no_grad():
            o = torch.empty_like(centres[fi])
            d = torch.empty_like(o)
            o[train], d[train] = drift.apply(centres[fi][train], d_telemetry[train], t01[fi][train],
                                             row_of[train] if rows else None)
            o[held], d[held] = drift.apply(centres[fi][held], d_telemetry[held], t01[fi][held])
            v = points - o
            return (v - (v * d).sum(-1, keepdim=True) * d).norm(dim=-1)

    knots = fit(PoseDrift(4))
    both = fit(PoseDrift(4, frame_t01=t01[0::2].tolist()))
    # measured: train 0.042 -> 0.005 m; held-out 0.087 -> 0.084 m (raw rows without the projection: 0.17)
    assert float(knots[train].median()) > 0.03
    assert float(both[train].median()) < 0.3 * float(knots[train].median())
    assert float(both[held].median()) < 1.1 * float(knots[held].median())
