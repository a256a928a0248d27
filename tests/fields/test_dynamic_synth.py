"""Dynamic synthesis (the paper's dynamic case): N trajectory points rendered at t and t ± Δt by a
fitted K-Planes field, boxes from its mask, and the Real / Synthetic / R+S datasets.

A 64x48 flight of 12 frames 0.5 s apart (people walking), extended K-Planes fitted for 3 steps.
"""

import numpy as np
import pytest

from fields.dynamic_data import load_dynamic_flight
from fields.dynamic_simscene import LineSpec, PoseNoise, write_line_flight
from fields.dynamic_training import DynamicFitConfig, fit_dynamic
from fields.synth_flight import synthesize_flight
from sim.world import make_world
from telemetry.camera import Camera, Mount
from telemetry.posesfile import PosesFile

SPEC = LineSpec(altitude_m=6.0, length_m=4.0, frames=12, dt_s=0.5)
TINY = dict(iters=3, budget_s=None, n_samples=8, batch_rays=128, max_resolution=32, features=4, hidden=16)


@pytest.fixture(scope="module")
def fitted_dynamic_flight(tmp_path_factory):
    flight = tmp_path_factory.mktemp("dynsynth") / "flight"
    world = make_world(seed=5, dynamic=True, texture_size=512, texel_m=0.05)
    write_line_flight(flight, world, Camera.from_fov(64, 48, 70.0, Mount(pitch_deg=-60)), SPEC, PoseNoise(),
                      supersample=1)
    fit_dynamic(load_dynamic_flight(flight), DynamicFitConfig(kind="kplanes-ext", **TINY),
                out_dir=flight / "derived" / "fields")
    return flight


def test_dynamic_synthesis_renders_3n_views_at_t_and_t_pm_dt(fitted_dynamic_flight):
    flight = fitted_dynamic_flight
    summary = synthesize_flight(flight, count=6)
    assert summary["images"] == 6 and summary["dropped_poses"] == 0
    synth = flight / "derived" / "synth"
    assert len(list((synth / "images").glob("*.jpg"))) == 6
    assert len(list((synth / "labels").glob("*.txt"))) == 6
    novel = PosesFile.load(synth / "poses.json").frames
    real_times = {e.t_unix_us for e in PosesFile.load(flight / "derived" / "poses.json").posed()}
    times = np.array([e.t_unix_us for e in novel]).reshape(2, 3)
    assert set(times[:, 1]) <= real_times  # the middle view of each triple is at a real frame's time
    np.testing.assert_array_equal(np.diff(times, axis=1), 500_000)  # Δt = one frame interval (0.5 s)
    assert all(e.source == "novel" and e.extra["dt_steps"] in (-1, 0, 1) for e in novel)
    for name in ("real", "synthetic", "r+s"):
        assert (flight / "derived" / "datasets" / name / "data.yaml").is_file()


def test_dynamic_synthesis_needs_two_capture_times(fitted_dynamic_flight, tmp_path):
    import shutil

    flight = tmp_path / "f"
    shutil.copytree(fitted_dynamic_flight, flight)
    pf = PosesFile.load(flight / "derived" / "poses.json")
    for e in pf.frames:
        e.t_unix_us = pf.frames[0].t_unix_us
    pf.save(flight / "derived" / "poses.json")
    with pytest.raises(ValueError, match="two distinct capture times"):
        synthesize_flight(flight, count=3)


def test_no_fitted_field_is_a_clear_error(tmp_path):
    (tmp_path / "derived" / "fields").mkdir(parents=True)
    with pytest.raises(FileNotFoundError, match="no fitted field"):
        synthesize_flight(tmp_path, count=3)


def test_replay_fits_kplanes_for_walking_people_and_synthesises_from_it(fitted_dynamic_flight, tmp_path):
    """`uavsim replay` (kind auto) on a flight whose labelled people walk: the fit stage chooses and fits
    extended K-Planes, the synth stage renders that field at trajectory times."""
    import shutil

    from agent.replay import ReplayOptions, stage_fit, stage_synth

    flight = tmp_path / "f"
    shutil.copytree(fitted_dynamic_flight, flight)
    shutil.rmtree(flight / "derived" / "fields")
    opts = ReplayOptions(kind="auto", fit_budget_s=2.0, synth_count=3)
    fitted = stage_fit(flight, opts)
    assert fitted["kind"] == "kplanes-ext" and fitted["kind_reason"]
    assert fitted["checkpoint"].endswith("dynamic.pt") and not (flight / "derived/fields/static.pt").exists()
    synth = stage_synth(flight, opts, fitted["checkpoint"])
    assert synth["images"] == 3
    with pytest.raises(ValueError, match="field kind"):
        stage_fit(flight, ReplayOptions(kind="nerf"))


def test_dynamic_synthesis_renders_at_drift_corrected_poses(fitted_dynamic_flight, tmp_path):
    """A field that learned a pose-drift correction renders the trajectory views (and lets the real
    labels vote) at the corrected poses, and the synthetic poses file says so."""
    import shutil

    from fields.dynamic_training import load_dynamic_checkpoint

    flight = tmp_path / "f"
    shutil.copytree(fitted_dynamic_flight, flight)
    fit_dynamic(load_dynamic_flight(flight), DynamicFitConfig(kind="kplanes-ext", pose_knot_s=2.0, **TINY),
                out_dir=flight / "derived" / "fields")
    model, _ = load_dynamic_checkpoint(flight / "derived" / "fields" / "dynamic.pt", "cpu")
    assert model.pose_drift is not None
    synthesize_flight(flight, count=3)
    real = {e.frame: e for e in PosesFile.load(flight / "derived" / "poses.json").posed()}
    for e in PosesFile.load(flight / "derived" / "synth" / "poses.json").frames:
        telemetry = real[e.extra["from_frame"]].cam_from_world
        np.testing.assert_allclose(e.cam_from_world, model.field_pose(telemetry, model.time01(e.t_unix_us)),
                                   atol=1e-6)
        assert not np.allclose(e.cam_from_world, telemetry, atol=1e-7)


def test_mask_threshold_outside_0_1_is_rejected(fitted_dynamic_flight):
    with pytest.raises(ValueError, match="mask threshold"):
        synthesize_flight(fitted_dynamic_flight, count=3, mask_threshold=1.5)
