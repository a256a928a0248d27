"""Dynamic fields: timed flight data, the K-Planes model and trainer, --kind auto, hard cases.

Flights are 64x48 px, 12 frames 0.5 s apart, from 6 m (people ~10 px tall) on a short line, so
walking people (1-1.6 m/s) move 3-5 m between frames >= 3 s apart.
"""

import json
import math
import shutil
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from fields.dynamic_data import load_dynamic_flight, normalise_times, time_resolution
from fields.dynamic_model import DynamicModel, density_bias_for, plane_sizing
from fields.dynamic_simscene import LineSpec, PoseNoise, noisy_poses, write_line_flight
from fields.dynamic_training import (
    AIR_MARGIN,
    DynamicFitConfig,
    air_density,
    build_model,
    evaluate_dynamic,
    fit_dynamic,
    gate_run_order,
    load_dynamic_checkpoint,
    ray_shortfall,
    shortfall_stats,
    split,
)
from fields.scene_kind import choose_kind
from sim.world import make_world
from telemetry.camera import Camera, Mount
from telemetry.posesfile import PosesFile

SPEC = LineSpec(altitude_m=6.0, length_m=4.0, frames=12, dt_s=0.5)
TINY = dict(iters=3, budget_s=None, n_samples=8, batch_rays=128, max_resolution=32, features=4, hidden=16)


def _flight(tmp_path_factory, dynamic: bool, seed: int = 5):
    out = tmp_path_factory.mktemp("dyn" if dynamic else "stat") / "flight"
    world = make_world(seed=seed, dynamic=dynamic, texture_size=512, texel_m=0.05)
    camera = Camera.from_fov(64, 48, 70.0, Mount(pitch_deg=-60))
    write_line_flight(out, world, camera, SPEC, PoseNoise(), supersample=1)
    return out


@pytest.fixture(scope="module")
def dynamic_flight(tmp_path_factory):
    return _flight(tmp_path_factory, True)


@pytest.fixture(scope="module")
def static_flight(tmp_path_factory):
    return _flight(tmp_path_factory, False)


def _choice(flight):
    dd = load_dynamic_flight(flight)
    d = dd.data
    return choose_kind(d.camera, d.cam_from_world, dd.times_us, d.boxes, d.has_mask.tolist())


# ---- --kind auto ------------------------------------------------------------------------------
def test_auto_picks_dynamic_when_people_walk(dynamic_flight):
    c = _choice(dynamic_flight)
    assert c.kind == "dynamic", c
    assert c.evidence["moved_fraction_long_gap"] > c.evidence["moved_fraction_short_gap"]


def test_auto_picks_static_when_people_stand(static_flight):
    c = _choice(static_flight)
    assert c.kind == "static", c
    assert "stay put" in c.reason


def test_auto_static_on_an_orbit_around_still_people(tiny_flight):
    """The shared static fixture (orbit, frames 0.2 s apart: 1.4 s) is too short to show motion."""
    c = _choice(tiny_flight)
    assert c.kind == "static" and "too short" in c.reason


def test_auto_without_labels_or_with_one_frame_is_static(static_flight):
    dd = load_dynamic_flight(static_flight)
    d = dd.data
    assert choose_kind(d.camera, d.cam_from_world, dd.times_us, None).kind == "static"
    one = choose_kind(d.camera, d.cam_from_world[:1], dd.times_us[:1], d.boxes[:1])
    assert one.kind == "static" and "single frame" in one.reason
    with pytest.raises(ValueError, match="one entry per frame"):
        choose_kind(d.camera, d.cam_from_world, dd.times_us[:3], d.boxes)


def test_cli_fit_auto_writes_the_choice_and_fits_extended(dynamic_flight, tmp_path):
    flight = tmp_path / "f"
    shutil.copytree(dynamic_flight, flight)
    out = tmp_path / "fields"
    r = subprocess.run([sys.executable, "-m", "agent.cli", "fit", str(flight), "--kind", "auto", "--iters", "2",
                        "--budget-s", "0", "--samples", "4", "--batch-rays", "64", "--out", str(out)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "--kind auto: dynamic" in r.stdout
    choice = json.loads((out / "kind.json").read_text())
    assert choice["kind"] == "dynamic"
    fit = json.loads((out / "fit.json").read_text())
    assert fit["kind"] == "kplanes-ext" and fit["kind_choice"]["kind"] == "dynamic"
    assert fit["planes"]["time_resolution"] == time_resolution(SPEC.frames) == 6
    assert len(fit["heldout"]["frames"]) == SPEC.frames // 2
    model, _ = load_dynamic_checkpoint(out / "dynamic.pt", "cpu")
    assert model.kind == "kplanes-ext"
    # render the fitted dynamic field at the paper's dynamic novel poses (t, t +- dt)
    from fields.novel_poses import dynamic_novel_poses

    pf = PosesFile.load(flight / "derived" / "poses.json")
    pf.frames = dynamic_novel_poses(pf.frames, 2, 2.0)
    pf.camera = pf.camera.scaled(0.5)
    pf.save(tmp_path / "novel.json")
    r = subprocess.run([sys.executable, "-m", "agent.cli", "render", str(flight),
                        "--poses", str(tmp_path / "novel.json"), "--out", str(tmp_path / "renders"),
                        "--checkpoint", str(out / "dynamic.pt"), "--masks"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert len(list((tmp_path / "renders").glob("pose_*_mask.png"))) == 6


# ---- data -------------------------------------------------------------------------------------
def test_times_normalise_and_alternate_split(dynamic_flight):
    dd = load_dynamic_flight(dynamic_flight)
    t = dd.t01()
    assert t[0] == 0.0 and t[-1] == 1.0 and np.all(np.diff(t) > 0)
    train, val = split(dd, 2)
    assert train == list(range(0, 12, 2)) and val == list(range(1, 12, 2))
    assert normalise_times(np.array([5, 5]), 5, 0).tolist() == [0.0, 0.0]
    assert normalise_times(np.array([-10, 50]), 0, 20).tolist() == [0.0, 1.0]
    assert time_resolution(1) == 2 and time_resolution(300) == 150


def test_out_of_order_timestamps(dynamic_flight, tmp_path):
    flight = tmp_path / "f"
    shutil.copytree(dynamic_flight, flight)
    pf = PosesFile.load(flight / "derived" / "poses.json")
    rng = np.random.default_rng(0)
    pf.frames = [pf.frames[i] for i in rng.permutation(len(pf.frames))]
    pf.save(flight / "derived" / "poses.json")
    dd = load_dynamic_flight(flight)
    by_name = dict(zip(dd.data.names, dd.t01(), strict=True))
    assert by_name["000000.png"] == 0.0 and by_name["000011.png"] == 1.0
    train, val = split(dd, 2)
    assert sorted(dd.data.names[i] for i in val) == [f"{k:06d}.png" for k in range(1, 12, 2)]
    r = fit_dynamic(dd, DynamicFitConfig(kind="kplanes", **TINY))
    assert r.step == 3


def test_missing_capture_time_is_a_clear_error(dynamic_flight, tmp_path):
    from fields.data import FlightDataError

    flight = tmp_path / "f"
    shutil.copytree(dynamic_flight, flight)
    pf = PosesFile.load(flight / "derived" / "poses.json")
    pf.frames[3].t_unix_us = None
    pf.save(flight / "derived" / "poses.json")
    dd = load_dynamic_flight(flight)  # falls back to frames.csv
    assert dd.times_us[3] == dd.times_us[2] + 500_000
    (flight / "frames.csv").write_text("frame,t_unix_us\n")
    with pytest.raises(FlightDataError, match="no capture time"):
        load_dynamic_flight(flight)


def test_noisy_poses_zero_noise_and_unsorted_times():
    poses = SPEC.true_poses()[:4]
    times = [1.5, 0.0, 1.0, 0.5]
    zero = PoseNoise(0, 0, 30, 0, 5, 0, 0)
    for a, b in zip(poses, noisy_poses(poses, times, zero), strict=True):
        assert np.allclose(a, b, atol=1e-9)
    noisy = noisy_poses(poses, times, PoseNoise())
    centres = [(-T[:3, :3].T @ T[:3, 3]) for T in noisy]
    true = [(-T[:3, :3].T @ T[:3, 3]) for T in poses]
    err = np.linalg.norm(np.array(centres) - np.array(true), axis=1)
    assert np.all(err > 0) and np.all(err < 5)


def test_plane_sizing_rejects_bad_extent():
    s = plane_sizing((40.0, 20.0, 5.0), 0.1, max_resolution=64)
    assert s.base_resolution == (16, 8, 2) and s.finest_cell_m == pytest.approx(40 / 64)
    with pytest.raises(ValueError, match="extent"):
        plane_sizing((np.nan, 1.0, 1.0), 0.1)


# ---- model and trainer ------------------------------------------------------------------------
def _model(dd, kind):
    cfg = DynamicFitConfig(kind=kind, **TINY)
    model, _, _ = build_model(dd, list(range(dd.n)), cfg, None)
    return model


@pytest.mark.parametrize("kind", ["kplanes", "kplanes-ext"])
def test_fit_gradients_finite_and_checkpoint_round_trip(dynamic_flight, tmp_path, kind):
    dd = load_dynamic_flight(dynamic_flight)
    r = fit_dynamic(dd, DynamicFitConfig(kind=kind, **TINY), out_dir=tmp_path)
    for p in r.model.parameters():
        assert torch.isfinite(p).all()
    model, ck = load_dynamic_checkpoint(tmp_path / "dynamic.pt", "cpu")
    assert ck["step"] == 3 and model.kind == kind
    assert not model.field_config.planes.time_gate  # telemetry poses: the time gate's default is off
    a = r.model.render_image(dd.data.camera.scaled(0.25), dd.data.cam_from_world[1], 0.3)
    b = model.render_image(dd.data.camera.scaled(0.25), dd.data.cam_from_world[1], 0.3)
    assert np.allclose(a["rgb"], b["rgb"], atol=1e-6)
    assert ("dynamic" in a) == (kind == "kplanes-ext")
    ev = evaluate_dynamic(model, dd, [1])
    assert np.isfinite(ev["psnr"])


def test_heldout_psnr_splits_into_boxes_and_background(dynamic_flight):
    """Per frame, full-frame MSE = f x box MSE + (1 - f) x background MSE, f = the box pixel fraction."""
    dd = load_dynamic_flight(dynamic_flight)
    frames = [i for i in range(dd.n) if 0 < float(dd.dynamic_masks()[i].float().mean()) < 1][:1]
    assert frames, "the tiny dynamic flight should have a frame with people in it"
    ev = evaluate_dynamic(_model(dd, "kplanes"), dd, frames)
    row = ev["frames"][0]
    f = row["box_fraction"]
    assert f == pytest.approx(float(dd.dynamic_masks()[frames[0]].float().mean()))
    mse = lambda db: 10 ** (-db / 10)  # noqa: E731
    assert mse(row["psnr"]) == pytest.approx(f * mse(row["box_psnr"]) + (1 - f) * mse(row["bg_psnr"]), rel=1e-6)
    assert ev["bg_psnr"] == pytest.approx(row["bg_psnr"]) and ev["box_fraction"] == pytest.approx(f)


def test_resume_continues_the_step_count(dynamic_flight, tmp_path):
    dd = load_dynamic_flight(dynamic_flight)
    fit_dynamic(dd, DynamicFitConfig(kind="kplanes-ext", **TINY), out_dir=tmp_path)
    r = fit_dynamic(dd, DynamicFitConfig(kind="kplanes-ext", **{**TINY, "iters": 5}), out_dir=tmp_path, resume=True)
    assert r.step == 5
    with pytest.raises(ValueError, match="holds a kplanes-ext"):
        fit_dynamic(dd, DynamicFitConfig(kind="kplanes", **TINY), out_dir=tmp_path, resume=True)


def test_resume_keeps_the_checkpoint_model_and_says_which_options_it_overrides(dynamic_flight, tmp_path, caplog):
    """A whole-box extended fit resumed under the default ground layer stays a whole-box fit, and the log
    names the option that did not take effect; options that do not shape the model pass silently."""
    dd = load_dynamic_flight(dynamic_flight)
    first = fit_dynamic(dd, DynamicFitConfig(kind="kplanes-ext", **TINY, dynamic_height_m=None), out_dir=tmp_path)
    assert first.model.field_config.planes.dynamic_z_top == 1.0
    caplog.set_level("WARNING", logger="fields.dynamic_training")
    r = fit_dynamic(dd, DynamicFitConfig(kind="kplanes-ext", **{**TINY, "iters": 5}), out_dir=tmp_path, resume=True)
    assert r.step == 5 and r.model.field_config.planes.dynamic_z_top == 1.0
    warned = [m for m in caplog.messages if "apply only to a fresh fit" in m]
    assert len(warned) == 1 and "dynamic_height_m: None -> 2.5" in warned[0] and "iters" not in warned[0]
    # the run's record states the model it trained: the checkpoint's layer, with the options that do not
    # shape the model as asked; so a second resume warns again
    assert r.config.dynamic_height_m is None and r.config.iters == 5
    saved = torch.load(tmp_path / "dynamic.pt", weights_only=False)["fit_config"]
    assert saved["dynamic_height_m"] is None and saved["iters"] == 5
    caplog.clear()
    fit_dynamic(dd, DynamicFitConfig(kind="kplanes-ext", **{**TINY, "iters": 6}), out_dir=tmp_path, resume=True)
    assert len([m for m in caplog.messages if "dynamic_height_m: None -> 2.5" in m]) == 1


#: a changed value for each option whose default is None, a string or a tuple (numbers and flags change
#: generically), and for ``cell_factor``, which must coarsen the cells past TINY's resolution cap to show
_OTHER_VALUE = {"budget_s": 10.0, "threads": 1, "mask_init_background": None, "mask_encoding": "geometry",
                "air_prior": True, "time_gate": True, "dynamic_height_m": None, "pose_knot_s": 2.0,
                "pose_knot_coarse_s": (8.0,), "cell_factor": 20.0}


def _changed(name: str, value):
    if name in _OTHER_VALUE:
        return _OTHER_VALUE[name]
    if isinstance(value, bool):
        return not value
    if isinstance(value, int):
        return value + 1
    if isinstance(value, float):
        return value * 2 + 0.125
    raise AssertionError(f"no changed value for option {name}={value!r}: add one to _OTHER_VALUE")


def test_model_options_lists_every_option_that_shapes_the_model(dynamic_flight):
    """``MODEL_OPTIONS`` is kept by hand beside ``build_model``; a resume warns only about the options in it.
    Changing any other option one at a time leaves the built model's description as it was, and changing
    a listed option other than the SfM-only one changes it (the flight has telemetry poses)."""
    from dataclasses import fields as dataclass_fields
    from dataclasses import replace

    from fields.description_diff import description_differences
    from fields.dynamic_training import MODEL_OPTIONS

    dd = load_dynamic_flight(dynamic_flight)
    train, _ = split(dd, 2)
    base = DynamicFitConfig(kind="kplanes-ext", **TINY)
    described = build_model(dd, train, base, dynamic_flight)[0].describe()
    unlisted_but_shaping, listed_but_inert = [], []
    for f in dataclass_fields(DynamicFitConfig):
        if f.name == "kind":
            continue
        other = replace(base, **{f.name: _changed(f.name, getattr(base, f.name))})
        diff = description_differences(described, build_model(dd, train, other, dynamic_flight)[0].describe())
        if diff and f.name not in MODEL_OPTIONS:
            unlisted_but_shaping.append((f.name, sorted(diff)))
        if not diff and f.name in MODEL_OPTIONS and f.name != "pose_drift_on_sfm":
            listed_but_inert.append(f.name)
    assert unlisted_but_shaping == [] and listed_but_inert == []


def test_options_the_checkpoint_overrides_compares_tuples_with_saved_lists():
    """torch.save keeps tuples, but an older checkpoint or a JSON round trip may hold lists."""
    from fields.dynamic_training import options_the_checkpoint_overrides

    cfg = DynamicFitConfig()
    saved = asdict(cfg) | {"pose_knot_coarse_s": list(cfg.pose_knot_coarse_s)}
    assert options_the_checkpoint_overrides(saved, cfg) == {}
    saved |= {"features": cfg.features * 2, "lr": 1.0}
    assert options_the_checkpoint_overrides(saved, cfg) == {"features": (cfg.features * 2, cfg.features)}
    assert options_the_checkpoint_overrides({}, cfg) == {}  # a checkpoint that predates fit_config


def _plane_grads(model, gate_value, dd):
    """Gradients of an RGB-only loss on the static and dynamic spatial planes for a constant gate."""
    from fields.data import RayBank

    torch.manual_seed(0)
    bank = RayBank(dd.data.camera, dd.data.cam_from_world)
    o, d = bank.rays(torch.zeros(256, dtype=torch.long), torch.randint(bank.hw, (256,)))
    gate = torch.full((256,), float(gate_value))
    res = model.render_rays(o, d, torch.full((256,), 0.5), dynamic_gate=gate, with_mask=False)
    model.zero_grad()
    res["rgb"].sum().backward()
    enc = model.field.encoding
    stat = sum(float(p.grad.abs().sum()) for p in enc.static_planes if p.grad is not None)
    dyn = sum(float(p.grad.abs().sum()) for p in enc.dynamic_planes if p.grad is not None)
    return stat, dyn


def test_all_dynamic_mask_updates_only_dynamic_planes(dynamic_flight):
    dd = load_dynamic_flight(dynamic_flight)
    model = _model(dd, "kplanes-ext")
    stat, dyn = _plane_grads(model, 1.0, dd)
    assert stat == 0.0 and dyn > 0.0


def test_empty_mask_updates_only_static_planes(dynamic_flight):
    dd = load_dynamic_flight(dynamic_flight)
    model = _model(dd, "kplanes-ext")
    stat, dyn = _plane_grads(model, 0.0, dd)
    assert stat > 0.0 and dyn == 0.0


def test_mixed_mask_static_planes_see_only_static_rays(dynamic_flight):
    """In one batch with both kinds of pixels, the static planes' gradient equals that of the static
    rays' loss alone and the dynamic planes' that of the dynamic rays' loss alone."""
    from fields.data import RayBank

    dd = load_dynamic_flight(dynamic_flight)
    model = _model(dd, "kplanes-ext")
    torch.manual_seed(1)
    bank = RayBank(dd.data.camera, dd.data.cam_from_world)
    o, d = bank.rays(torch.zeros(64, dtype=torch.long), torch.randint(bank.hw, (64,)))
    gate = (torch.arange(64) % 3 == 0).float()
    enc = model.field.encoding

    def grads(weight):
        model.zero_grad()
        res = model.render_rays(o, d, torch.full((64,), 0.5), dynamic_gate=gate, with_mask=False)
        (res["rgb"].sum(-1) * weight).sum().backward()
        return ([p.grad.clone() for p in enc.static_planes], [p.grad.clone() for p in enc.dynamic_planes])

    s_all, d_all = grads(torch.ones(64))
    s_static, _ = grads(1 - gate)
    _, d_dyn = grads(gate)
    for a, b in zip(s_all, s_static, strict=True):
        assert torch.allclose(a, b, atol=1e-6)
    for a, b in zip(d_all, d_dyn, strict=True):
        assert torch.allclose(a, b, atol=1e-6)
    assert sum(float(g.abs().sum()) for g in s_all) > 0 and sum(float(g.abs().sum()) for g in d_all) > 0


def test_flight_without_people_trains_the_extended_model(dynamic_flight, tmp_path):
    """Empty label files (no person anywhere): all pixels static, the mask target is all zero."""
    flight = tmp_path / "f"
    shutil.copytree(dynamic_flight, flight)
    for p in (flight / "labels").glob("*.txt"):
        p.write_text("")
    dd = load_dynamic_flight(flight)
    assert not dd.dynamic_masks().any()
    r = fit_dynamic(dd, DynamicFitConfig(kind="kplanes-ext", **TINY))
    assert all(torch.isfinite(p).all() for p in r.model.parameters())


def test_single_frame_flight(dynamic_flight, tmp_path):
    flight = tmp_path / "f"
    shutil.copytree(dynamic_flight, flight)
    pf = PosesFile.load(flight / "derived" / "poses.json")
    pf.frames = pf.frames[:1]
    pf.save(flight / "derived" / "poses.json")
    dd = load_dynamic_flight(flight)
    assert dd.n == 1 and dd.t01().tolist() == [0.0]
    assert split(dd, 2) == ([0], [])
    r = fit_dynamic(dd, DynamicFitConfig(kind="kplanes-ext", **TINY))
    assert r.model.field_config.planes.time_resolution == 2
    assert r.model.time01(None) == 0.0


def test_model_rejects_mismatched_kind(dynamic_flight):
    dd = load_dynamic_flight(dynamic_flight)
    m = _model(dd, "kplanes")
    with pytest.raises(ValueError, match="does not match"):
        DynamicModel("kplanes-ext", m.field_config, m.sampler_config, 0.0, 10.0)


# ---- the class mask (synthetic labels come from it) -------------------------------------------
def test_a_fresh_kplanes_mask_can_start_as_background(dynamic_flight):
    """``mask_init_background``: an untrained dynamic field renders no boxes; torch's default start
    (~uniform over 4 outputs) renders foreground 0.75 wherever the field is opaque."""
    from fields.mask_boxes import boxes_from_probabilities

    dd = load_dynamic_flight(dynamic_flight)
    cam = dd.data.camera.scaled(0.5)
    for start, blobs in ((0.99, False), (None, True)):
        cfg = DynamicFitConfig(kind="kplanes-ext", mask_init_background=start, **TINY)
        torch.manual_seed(0)
        model, _, _ = build_model(dd, list(range(dd.n)), cfg, None)
        probs = model.eval().render_image(cam, dd.data.cam_from_world[0], 0.5)["mask_probs"]
        assert probs.shape == (cam.height, cam.width, 4)
        assert np.allclose(probs.sum(-1), 1.0, atol=1e-5)
        assert bool(boxes_from_probabilities(probs)) == blobs
        if start is not None:
            assert probs[..., 0].min() > 0.97


def test_box_rays_fit_stays_finite_and_ray_runs_change_nothing_but_speed(dynamic_flight):
    """With box rays and mask losses the fit stays finite; ordering the rays into the gated encoding's
    runs (``gate_ray_runs``) keeps each ray's jitter, so the same seed fits the same parameters."""
    dd = load_dynamic_flight(dynamic_flight)
    fits = []
    for runs in (False, True):
        cfg = DynamicFitConfig(kind="kplanes-ext", box_ray_fraction=0.5, mask_init_background=0.99,
                               gate_ray_runs=runs, **TINY)
        fits.append(fit_dynamic(dd, cfg))
    for r in fits:
        assert r.step == 3 and all(torch.isfinite(p).all() for p in r.model.parameters())
    for a, b in zip(fits[0].model.parameters(), fits[1].model.parameters(), strict=True):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-6)


def test_gate_run_order_hand_values():
    """The leading rays as drawn, then the static rays, then the dynamic ones, each in drawn order."""
    dynamic = torch.tensor([True, False, True, False, True, True, False])
    assert gate_run_order(dynamic, 2).tolist() == [0, 1, 3, 6, 2, 4, 5]
    assert gate_run_order(dynamic, 0).tolist() == [1, 3, 6, 0, 2, 4, 5]
    assert gate_run_order(dynamic, 99).tolist() == list(range(7))
    assert gate_run_order(torch.zeros(0, dtype=torch.bool), 4).tolist() == []


def test_heldout_mask_boxes_of_a_perfect_mask_match_every_separate_person(dynamic_flight):
    """evaluate_dynamic's box scores on a stand-in model that renders the frame itself and its
    filled label boxes as a hard mask: every person whose box touches no other is found exactly."""
    from scipy import ndimage

    dd = load_dynamic_flight(dynamic_flight)
    data = dd.data

    class Perfect:
        def field_pose(self, cam_from_world, time01):  # no learned pose correction
            return cam_from_world

        def render_image(self, camera, cam_from_world, time01):
            i = next(k for k in range(data.n) if np.array_equal(data.cam_from_world[k], cam_from_world))
            m = data.masks[i].numpy().astype(int)
            return {"rgb": data.images[i].numpy() / 255.0, "mask_probs": np.eye(4, dtype=np.float32)[m]}

    def separate(i):
        n_blobs = ndimage.label(data.masks[i].numpy() > 0, structure=np.ones((3, 3)))[1]
        return bool(data.boxes[i]) and n_blobs == len(data.boxes[i])

    frames = [i for i in range(data.n) if separate(i)]
    assert frames, "the tiny flight should have a frame whose people do not touch"
    ev = evaluate_dynamic(Perfect(), dd, frames, min_box_px=2.0)
    assert ev["box_iou_mean"] == pytest.approx(1.0, abs=1e-3)  # label edges are sub-pixel
    assert ev["mask_recall"] == 1.0 and ev["mask_precision"] == 1.0
    assert ev["psnr"] > 60


def test_mask_planes_read_the_geometry_and_never_change_it(dynamic_flight):
    """``mask_encoding="planes"``: same seed, same colour and density after training as without the
    mask planes (the mask is composited with detached weights on its own planes), and the mask
    planes move only through the mask loss."""
    dd = load_dynamic_flight(dynamic_flight)
    cam = dd.data.camera.scaled(0.5)
    renders = {}
    for enc in ("geometry", "planes"):
        torch.manual_seed(0)
        cfg = DynamicFitConfig(kind="kplanes-ext", mask_encoding=enc, mask_init_background=0.99,
                               box_ray_fraction=0.25, **TINY)
        r = fit_dynamic(dd, cfg)
        renders[enc] = r.model.render_image(cam, dd.data.cam_from_world[2], 0.4)
        if enc == "planes":
            model = r.model
    assert np.allclose(renders["geometry"]["rgb"], renders["planes"]["rgb"], atol=1e-6)
    assert renders["planes"]["mask_probs"].shape[-1] == 4
    from fields.data import RayBank

    bank = RayBank(dd.data.camera, dd.data.cam_from_world)
    o, d = bank.rays(torch.zeros(64, dtype=torch.long), torch.randint(bank.hw, (64,)))
    model.train()
    res = model.render_rays(o, d, torch.full((64,), 0.5), with_mask=True)
    model.zero_grad()
    res["rgb"].sum().backward(retain_graph=True)
    assert all(p.grad is None or float(p.grad.abs().sum()) == 0.0 for p in model.field.mask_planes.parameters())
    res["mask_probs"][:, 1:].sum().backward()
    assert sum(float(p.grad.abs().sum()) for p in model.field.mask_planes.parameters() if p.grad is not None) > 0


def test_fit_with_pose_drift_moves_the_knots_and_round_trips(dynamic_flight, tmp_path):
    """One knot per 2 s over the 5.5 s flight; the knots get gradients from the first step, stay
    finite, survive save → load → resume, and the held-out frames render at the corrected pose."""
    dd = load_dynamic_flight(dynamic_flight)
    cfg = DynamicFitConfig(kind="kplanes-ext", pose_knot_s=2.0, **TINY)
    r = fit_dynamic(dd, cfg, out_dir=tmp_path)
    drift = r.model.pose_drift
    assert drift is not None and drift.knots == 4
    assert torch.isfinite(drift.trans).all() and torch.isfinite(drift.rot).all()
    assert float(drift.trans.detach().abs().max()) > 0 and float(drift.rot.detach().abs().max()) > 0
    model, _ = load_dynamic_checkpoint(tmp_path / "dynamic.pt", "cpu")
    assert torch.equal(model.pose_drift.trans, drift.trans)
    T = dd.data.cam_from_world[1]
    assert not np.allclose(model.field_pose(T, 0.3), T, atol=1e-7)
    assert np.isfinite(evaluate_dynamic(model, dd, [1])["psnr"])
    again = fit_dynamic(dd, DynamicFitConfig(kind="kplanes-ext", pose_knot_s=2.0, **{**TINY, "iters": 5}),
                        out_dir=tmp_path, resume=True)
    assert again.step == 5 and again.model.pose_drift.knots == 4

    no_drift = build_model(dd, list(range(dd.n)), DynamicFitConfig(kind="kplanes", pose_knot_s=None, **TINY), None)[0]
    assert no_drift.pose_drift is None and np.array_equal(no_drift.field_pose(T, 0.3), T)


def test_fit_with_per_frame_pose_rows_trains_the_training_frames_rows_only(dynamic_flight, tmp_path):
    """pose_per_frame: one row per training frame; the rows learn, survive save -> load -> resume; a
    training frame's field pose includes its row, a held-out frame's is the knots' alone."""
    from fields.pose_drift import PoseDrift

    dd = load_dynamic_flight(dynamic_flight)
    cfg = DynamicFitConfig(kind="kplanes-ext", pose_knot_s=2.0, pose_per_frame=True, pose_delay=0.0,
                           **{**TINY, "iters": 4})
    train_idx, val_idx = split(dd, cfg.holdout_every)
    r = fit_dynamic(dd, cfg, out_dir=tmp_path)
    drift = r.model.pose_drift
    assert drift.frames == len(train_idx) and np.allclose(drift.frame_t01.numpy(), dd.t01()[train_idx])
    assert torch.isfinite(drift.frame_trans).all() and float(drift.frame_residual()[1].detach().abs().max()) > 0
    assert any("one correction per training frame" in line for line in r.sizing["reasoning"])
    model, _ = load_dynamic_checkpoint(tmp_path / "dynamic.pt", "cpu")
    assert torch.equal(model.pose_drift.frame_trans, drift.frame_trans)
    knots_only = PoseDrift(drift.knots, drift.coarse_knots)
    knots_only.load_state_dict({k: v for k, v in drift.state_dict().items() if not k.startswith("frame_")})
    t01 = dd.t01()
    for i in (train_idx[1], val_idx[1]):
        T = dd.data.cam_from_world[i]
        same = np.allclose(model.field_pose(T, float(t01[i])), knots_only.correct_cam_from_world(T, float(t01[i])),
                           atol=1e-9)
        assert same == (i in val_idx)
    again = fit_dynamic(dd, DynamicFitConfig(kind="kplanes-ext", pose_knot_s=2.0, pose_per_frame=True,
                                             **{**TINY, "iters": 6}), out_dir=tmp_path, resume=True)
    assert again.step == 6 and again.model.pose_drift.frames == len(train_idx)


def test_fit_with_coarse_pose_knot_levels_moves_every_level_and_round_trips(dynamic_flight, tmp_path):
    """A 2 s level under the 1 s knots: both levels learn, fit.json says why, the checkpoint keeps both."""
    from fields.dynamic_training import pose_knots

    dd = load_dynamic_flight(dynamic_flight)
    cfg = DynamicFitConfig(kind="kplanes", pose_knot_s=1.0, pose_knot_coarse_s=(2.0,), **TINY)
    knots, coarse, why = pose_knots(dd, cfg)
    assert (knots, coarse) == (7, [4]) and "4 knots (2 s)" in why
    r = fit_dynamic(dd, cfg, out_dir=tmp_path)
    drift = r.model.pose_drift
    assert drift.coarse_knots == [4]
    assert float(drift.trans.detach().abs().max()) > 0 and float(drift.coarse_trans[0].detach().abs().max()) > 0
    assert float(drift.coarse_rot[0].detach().abs().max()) > 0
    assert any("4 knots (2 s)" in line for line in r.sizing["reasoning"])
    model, _ = load_dynamic_checkpoint(tmp_path / "dynamic.pt", "cpu")
    assert model.pose_drift.coarse_knots == [4]
    assert torch.equal(model.pose_drift.coarse_trans[0], drift.coarse_trans[0])
    T = dd.data.cam_from_world[2]
    np.testing.assert_allclose(model.field_pose(T, 0.4), r.model.field_pose(T, 0.4), atol=1e-12)


def test_pose_delay_keeps_the_knots_still_while_the_field_learns(dynamic_flight):
    """pose_delay 0.5: over 2 steps (progress 0, 0.5) the knots stay exactly at zero while the field
    moves; a third step (progress 2/3, step-size factor 1/3) moves them."""
    dd = load_dynamic_flight(dynamic_flight)
    frozen = fit_dynamic(dd, DynamicFitConfig(kind="kplanes", pose_knot_s=2.0, pose_delay=0.5,
                                              **{**TINY, "iters": 2}))
    assert not frozen.model.pose_drift.trans.any() and not frozen.model.pose_drift.rot.any()
    torch.manual_seed(0)  # the fit's seed: the same initial field
    cfg = DynamicFitConfig(kind="kplanes", pose_knot_s=2.0, **TINY)
    start = dict(build_model(dd, split(dd, cfg.holdout_every)[0], cfg, None)[0].field.named_parameters())
    assert any(not torch.equal(p, start[n]) for n, p in frozen.model.field.named_parameters())
    thawed = fit_dynamic(dd, DynamicFitConfig(kind="kplanes", pose_knot_s=2.0, pose_delay=0.5, **TINY))
    assert float(thawed.model.pose_drift.trans.detach().abs().max()) > 0


def test_cli_fit_with_pose_knots_and_render_recorded_poses_at_the_corrected_pose(dynamic_flight, tmp_path):
    """`uavsim fit --pose-knot-s` learns the drift (reported in fit.json); `uavsim render` draws a
    recorded (telemetry) pose at its corrected pose."""
    import cv2

    from fields.field_views import load_view_renderer

    out = tmp_path / "fields"
    r = subprocess.run([sys.executable, "-m", "agent.cli", "fit", str(dynamic_flight), "--kind", "kplanes-ext",
                        "--iters", "2", "--budget-s", "0", "--samples", "4", "--batch-rays", "64",
                        "--pose-knot-s", "2", "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert json.loads((out / "fit.json").read_text())["pose_drift"]["knots"] == 4
    pf = PosesFile.load(dynamic_flight / "derived" / "poses.json")
    pf.frames = pf.frames[3:4]
    pf.camera = pf.camera.scaled(0.5)
    pf.save(tmp_path / "one.json")
    r = subprocess.run([sys.executable, "-m", "agent.cli", "render", str(dynamic_flight), "--poses",
                        str(tmp_path / "one.json"), "--out", str(tmp_path / "renders"), "--checkpoint",
                        str(out / "dynamic.pt")], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    got = cv2.cvtColor(cv2.imread(str(tmp_path / "renders" / (pf.frames[0].frame.rsplit(".", 1)[0] + ".png"))),
                       cv2.COLOR_BGR2RGB)
    renderer = load_view_renderer(out / "dynamic.pt", dynamic_flight)
    m, e = renderer.model, pf.frames[0]
    want, _ = renderer.render_view(pf.camera, m.field_pose(e.cam_from_world, m.time01(e.t_unix_us)), e.t_unix_us,
                                   with_mask=False)
    np.testing.assert_array_equal(got, want)


def _sfm_copy(flight: Path, tmp_path: Path) -> Path:
    """A copy of ``flight`` whose every pose is marked SfM-refined (``source`` "sfm")."""
    copy = tmp_path / "f"
    shutil.copytree(flight, copy)
    pf = PosesFile.load(copy / "derived" / "poses.json")
    for e in pf.frames:
        e.source = "sfm"
    pf.save(copy / "derived" / "poses.json")
    return copy


def test_pose_drift_is_learned_on_telemetry_poses_and_not_on_sfm_refined_ones(dynamic_flight, tmp_path):
    from fields.dynamic_training import pose_knots, time_gate

    dd = load_dynamic_flight(dynamic_flight)
    assert set(dd.pose_sources) == {"telemetry"} and not dd.all_poses_sfm
    knots, coarse, why = pose_knots(dd, DynamicFitConfig(kind="kplanes"))
    assert knots == 7 and coarse == [3, 2] and "one per 1 s" in why  # 5.5 s of flight; levels of 4 s and 15 s
    assert "first 10% of training" in why
    assert pose_knots(dd, DynamicFitConfig(pose_knot_coarse_s=(), pose_delay=0.0)) == (7, [], "pose drift: 7 knots, "
                                                                                          "one per 1 s of flight")
    flight = _sfm_copy(dynamic_flight, tmp_path)
    pf = PosesFile.load(flight / "derived" / "poses.json")
    sfm = load_dynamic_flight(flight)
    assert sfm.all_poses_sfm
    knots, _, why = pose_knots(sfm, DynamicFitConfig(kind="kplanes"))
    assert knots == 0 and "SfM-refined" in why
    assert pose_knots(sfm, DynamicFitConfig(pose_drift_on_sfm=True))[0] == 7
    assert pose_knots(dd, DynamicFitConfig(pose_knot_s=None))[0] == 0
    r = fit_dynamic(sfm, DynamicFitConfig(kind="kplanes-ext", **TINY))
    assert r.model.pose_drift is None and any("SfM-refined" in line for line in r.sizing["reasoning"])
    # the time gate follows the same evidence: on for SfM-refined poses, off for telemetry, or as set
    assert r.model.field_config.planes.time_gate
    assert any(line.startswith("time gate: on") for line in r.sizing["reasoning"])
    # the dynamic planes span the ground layer by default, sized from the scene box
    layer = [line for line in r.sizing["reasoning"] if line.startswith("dynamic planes:")]
    z_top = r.model.field_config.planes.dynamic_z_top
    assert len(layer) == 1 and 0 < z_top <= 1 and (z_top == 1) == ("whole box" in layer[0])
    assert time_gate(sfm, DynamicFitConfig())[0] and not time_gate(dd, DynamicFitConfig())[0]
    assert time_gate(dd, DynamicFitConfig(time_gate=True)) == (True, "time gate: on (set explicitly)")
    assert not time_gate(sfm, DynamicFitConfig(time_gate=False))[0]
    # one frame left to telemetry (SfM could not register it): its pose may drift, so learn the correction
    pf.frames[3].source = "telemetry"
    pf.save(flight / "derived" / "poses.json")
    assert pose_knots(load_dynamic_flight(flight), DynamicFitConfig())[0] == 7
    for f in pf.frames:
        f.source = "sfm"
    pf.save(flight / "derived" / "poses.json")
    from fields.dynamic_cli import fit_dynamic_flight

    fit_dynamic_flight(flight, tmp_path / "out", "kplanes", budget_s=None, iters=2, samples=8, batch_rays=128,
                       pose_knot_s=2.0)  # an explicit spacing (uavsim fit --pose-knot-s 2) holds on SfM poses
    assert json.loads((tmp_path / "out" / "fit.json").read_text())["pose_drift"]["knots"] == 4


def test_air_density_samples_the_upper_box_at_all_times_and_the_fit_stays_finite(dynamic_flight):
    dd = load_dynamic_flight(dynamic_flight)
    model = _model(dd, "kplanes-ext")
    seen = {}
    density = model.field.density

    def spy(points, times01):
        seen["points"], seen["times"] = points, times01
        return density(points, times01)

    model.field.density = spy
    sigma = air_density(model.field, 500, 0.3, torch.Generator().manual_seed(0))
    lo, hi = model.field.lo, model.field.hi
    z01 = (seen["points"][:, 2] - lo[2]) / (hi[2] - lo[2])
    assert sigma.shape == (500,) and (sigma >= 0).all() and (sigma <= 10).all()
    assert float(z01.min()) >= 0.3 - 1e-6 and float(z01.max()) <= 1.0
    assert ((seen["points"] >= lo) & (seen["points"] <= hi)).all()
    assert 0 <= float(seen["times"].min()) and float(seen["times"].max()) <= 1
    r = fit_dynamic(dd, DynamicFitConfig(kind="kplanes", lambda_empty=0.01, **TINY))
    assert all(torch.isfinite(p).all() for p in r.model.parameters())


@pytest.mark.parametrize(("window", "expected_steps"), [
    ({}, 9),  # the defaults: steps 1..9 of 10, shares 0.1 .. 0.9
    ({"empty_from": 0.0, "empty_until": 0.3}, 3),  # steps 0, 1, 2: shares 0, 0.1, 0.2 < 0.3
    ({"empty_from": 0.0}, 10),  # throughout
    ({"empty_from": 0.3, "empty_until": 0.8}, 5),  # steps 3..7: shares 0.3 .. 0.7
    ({"lambda_empty": 0.0}, 0),  # off
    ({"air_prior": False}, 0),  # off
    ({"air_prior": True, "lambda_empty": 0.0}, 0),  # no weight: off
])
def test_air_prior_acts_in_its_window_of_training(dynamic_flight, monkeypatch, window, expected_steps):
    import fields.dynamic_training as training

    calls = []

    def counting(field, n, above, generator):
        calls.append(n)
        return air_density(field, n, above, generator)

    monkeypatch.setattr(training, "air_density", counting)
    dd = load_dynamic_flight(dynamic_flight)
    r = fit_dynamic(dd, DynamicFitConfig(kind="kplanes", **window, **{**TINY, "iters": 10}))
    assert len(calls) == expected_steps and r.air_prior_steps == expected_steps


def test_air_prior_acts_on_telemetry_poses_and_not_on_sfm_refined_ones(dynamic_flight, tmp_path):
    from fields.dynamic_training import air_prior

    dd = load_dynamic_flight(dynamic_flight)
    sfm = load_dynamic_flight(_sfm_copy(dynamic_flight, tmp_path))
    on, why = air_prior(dd, DynamicFitConfig())
    assert on and why.startswith("air prior: on from 10% of training, the poses are telemetry")
    on, why = air_prior(sfm, DynamicFitConfig())
    assert not on and why.startswith(f"air prior: off, all {sfm.n} poses are SfM-refined")
    assert air_prior(sfm, DynamicFitConfig(air_prior=True)) == (True, "air prior: on (set explicitly)")
    assert air_prior(dd, DynamicFitConfig(air_prior=False)) == (False, "air prior: off (set explicitly)")
    no_weight = DynamicFitConfig(air_prior=True, lambda_empty=0.0)
    assert air_prior(dd, no_weight) == (False, "air prior: off (lambda_empty 0)")
    cfg = {**TINY, "iters": 10}
    r = fit_dynamic(sfm, DynamicFitConfig(kind="kplanes", **cfg))
    assert r.air_prior_steps == 0 and any(line.startswith("air prior: off") for line in r.sizing["reasoning"])
    assert fit_dynamic(sfm, DynamicFitConfig(kind="kplanes", air_prior=True, **cfg)).air_prior_steps == 9


def test_cli_fit_air_prior_switch_overrides_the_pose_source_rule(dynamic_flight, tmp_path):
    from agent.cli import main

    out = tmp_path / "out"
    assert main(["fit", str(dynamic_flight), "--kind", "kplanes", "--iters", "10", "--budget-s", "0", "--samples",
                 "8", "--batch-rays", "128", "--air-prior", "off", "--out", str(out)]) == 0
    fit = json.loads((out / "fit.json").read_text())
    assert fit["air_prior_steps"] == 0 and fit["config"]["air_prior"] is False
    assert "air prior: off (set explicitly)" in fit["sizing"]["reasoning"]


def test_ray_shortfall_on_hand_computed_rays():
    # from 10 m above the ground plane z = 2: straight down (ground 10 m away) and 60 deg below the
    # horizon (ground 10 / sin 60 deg = 11.547 m away)
    s60, c60 = np.sin(np.pi / 3), np.cos(np.pi / 3)
    origins = torch.tensor([[0.0, 0.0, 12.0]] * 4)
    dirs = torch.tensor([[0.0, 0.0, -1.0], [c60, 0.0, -s60], [0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    keep = torch.tensor([True, True, True, False])
    on_ground = torch.tensor([10.0, 10.0 / s60, 10.0, 1.0])
    assert ray_shortfall(on_ground, origins, dirs, 2.0, keep).tolist() == pytest.approx([0.0] * 3, abs=1e-6)
    assert shortfall_stats(ray_shortfall(on_ground, origins, dirs, 2.0, keep)) == pytest.approx((0.0, 0.0), abs=1e-6)
    # a layer a third of the way down on every kept ray; the dropped ray's depth never counts
    layer = torch.tensor([[10 / 3], [10 / 3 / s60], [10 / 3], [1e9]])
    assert shortfall_stats(ray_shortfall(layer, origins, dirs, 2.0, keep)) == pytest.approx((2 / 3, 1.0), abs=1e-5)
    # one short ray of three (a tree) leaves the median on the ground and puts a third in the air
    tree = torch.tensor([10.0, 2.0, 10.0, 0.0])
    assert shortfall_stats(ray_shortfall(tree, origins, dirs, 2.0, keep)) == pytest.approx((0.0, 1 / 3), abs=1e-6)
    # a roof 3 m up: 30 % short, not in the air; beyond the plane: negative
    roof_and_far = torch.tensor([7.0, 20.0 / s60, 7.0, 0.0])
    median, in_air = shortfall_stats(ray_shortfall(roof_and_far, origins, dirs, 2.0, keep))
    assert median == pytest.approx(0.3, abs=1e-6) and in_air == 0.0
    assert ray_shortfall(roof_and_far, origins, dirs, 2.0, keep)[1] == pytest.approx(-1.0, abs=1e-5)


def test_ray_shortfall_skips_rays_that_cannot_meet_the_ground():
    origins = torch.tensor([[0.0, 0.0, 12.0], [0.0, 0.0, 12.0], [0.0, 0.0, 1.0], [0.0, 0.0, 12.0]])
    dirs = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    depth = torch.tensor([5.0, 5.0, 5.0, float("nan")])
    # looking up, level, starting below the plane, a NaN depth: no ray left
    assert ray_shortfall(depth, origins, dirs, 2.0, torch.ones(4, dtype=torch.bool)).numel() == 0
    assert shortfall_stats(ray_shortfall(depth, origins, dirs, 2.0, torch.ones(4, dtype=torch.bool))) is None
    assert ray_shortfall(depth[:0], origins[:0], dirs[:0], 2.0, torch.zeros(0, dtype=torch.bool)).numel() == 0


@pytest.mark.parametrize("shortfall", [0.5, 0.01])
def test_fit_logs_the_running_shortfall_of_its_background_rays(dynamic_flight, monkeypatch, shortfall):
    import fields.dynamic_training as training

    # every background ray of every batch ends ``shortfall`` short of the ground
    monkeypatch.setattr(training, "ray_shortfall", lambda *a: torch.full((8,), shortfall))
    dd = load_dynamic_flight(dynamic_flight)
    cfg = {**TINY, "iters": 6, "log_every_s": 0.0}
    r = fit_dynamic(dd, DynamicFitConfig(kind="kplanes", **cfg))
    assert r.ground_shortfall == pytest.approx(shortfall)
    assert r.air_share == pytest.approx(1.0 if shortfall > AIR_MARGIN else 0.0)
    assert r.curve[-1]["ground_shortfall"] == pytest.approx(shortfall, abs=1e-4)
    assert r.curve[-1]["air_share"] == r.air_share


def test_fit_reports_the_ground_shortfall_of_its_rays(dynamic_flight):
    dd = load_dynamic_flight(dynamic_flight)
    r = fit_dynamic(dd, DynamicFitConfig(kind="kplanes-ext", **{**TINY, "log_every_s": 0.0}))
    assert r.ground_shortfall is not None and np.isfinite(r.ground_shortfall) and r.ground_shortfall < 1.0
    assert 0.0 <= r.air_share <= 1.0
    assert r.air_prior_steps == 2  # the prior is on from 10 % of training: steps 1 and 2 of 3
    assert all("ground_shortfall" in c for c in r.curve)


@given(tau=st.floats(1e-3, 10.0), lo=st.floats(-100.0, 100.0), height=st.floats(0.1, 500.0))
def test_density_bias_for_gives_the_asked_optical_depth(tau, lo, height):
    """A field of density exp(bias) (1/m) everywhere has optical depth ``tau`` from box top to floor."""
    bias = density_bias_for(tau, lo, lo + height)
    assert math.exp(bias) * height == pytest.approx(tau, rel=1e-6)


@pytest.mark.parametrize("args", [(0.0, 0.0, 10.0), (-1.0, 0.0, 10.0), (float("nan"), 0.0, 10.0),
                                  (float("inf"), 0.0, 10.0), (0.2, 5.0, 5.0), (0.2, 5.0, 1.0),
                                  (0.2, 0.0, float("inf"))])
def test_density_bias_for_refuses_what_has_no_optical_depth(args):
    with pytest.raises(ValueError):
        density_bias_for(*args)


@pytest.mark.parametrize("kind", ["kplanes", "kplanes-ext"])
def test_fresh_field_lets_rays_reach_the_floor(dynamic_flight, kind):
    """With the default initial optical depth the fresh field is nearly transparent: the training rays
    reach the box floor (which ends them opaque) with most of their weight. The field's own bias of -1
    started it as fog that stopped them in the air (bench/RESULTS.md, Table III session 32)."""
    from fields.data import RayBank

    dd = load_dynamic_flight(dynamic_flight)
    train, _ = split(dd, 2)
    gen = torch.Generator().manual_seed(0)
    bank = RayBank(dd.data.camera, dd.data.cam_from_world)
    frames = torch.tensor(train)[torch.randint(len(train), (512,), generator=gen)]
    o, d = bank.rays(frames, torch.randint(bank.hw, (512,), generator=gen))

    def floor_weight(cfg: DynamicFitConfig) -> tuple[float, list[str]]:
        """The median ray's weight on the floor sample, and fit.json's sizing reasoning."""
        torch.manual_seed(0)
        model, _, sizing = build_model(dd, train, cfg, dynamic_flight)
        with torch.no_grad():
            res = model.render_rays(o, d, torch.full((512,), 0.5), with_mask=False)
        return float(res["weights"][:, -1].median()), sizing["reasoning"]

    transparent, reasoning = floor_weight(DynamicFitConfig(kind=kind, **TINY))
    fog, _ = floor_weight(DynamicFitConfig(kind=kind, init_optical_depth=None, **TINY))
    assert transparent > 0.6 and fog < 0.3  # measured 0.80 / 0.81 and 0.18 / 0.20 (kplanes / kplanes-ext)
    assert any(line.startswith("fresh field: optical depth 0.2 through the box") for line in reasoning)
