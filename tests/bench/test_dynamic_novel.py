"""Scoring dynamic fits from higher up (bench/dynamic_novel.py, also run by bench/dynamic.py).

A tiny simulated line flight: 64x48 px, 12 frames 0.5 s apart from 6 m, rendered as the bench renders its
flights (supersample 2), so a truth view at the frame's own pose must reproduce the recorded frame exactly.
"""

import math

import numpy as np
import pytest

from bench.dynamic_novel import novel_views, score_novel_views
from fields.dynamic_data import load_dynamic_flight
from fields.dynamic_simscene import LineSpec, PoseNoise, write_line_flight
from fields.dynamic_training import DynamicFitConfig, fit_dynamic, split
from sim.world import make_world
from telemetry.camera import Camera, Mount


@pytest.fixture(scope="module")
def flight_and_world(tmp_path_factory):
    out = tmp_path_factory.mktemp("novel") / "flight"
    world = make_world(seed=5, dynamic=True, texture_size=512, texel_m=0.05)
    camera = Camera.from_fov(64, 48, 70.0, Mount(pitch_deg=-60))
    write_line_flight(out, world, camera, LineSpec(altitude_m=6.0, length_m=4.0, frames=12, dt_s=0.5), PoseNoise(),
                      supersample=2)
    return out, world


def test_truth_at_the_frames_own_distance_is_the_recorded_frame(flight_and_world):
    # the truth view must be rendered at the frame's true pose *and* its scene time: the people walk
    # 0.5-0.8 m between frames, several pixels at 6 m, so a wrong time or the noisy pose would show
    flight, world = flight_and_world
    dd = load_dynamic_flight(flight)
    train_idx, val_idx = split(dd, 2)
    views = novel_views(flight, dd, train_idx, val_idx, world, scale=1.0, every=1)
    assert views.picked == val_idx
    for i in views.picked:
        assert np.array_equal(views.truth_rgb[i], dd.data.images[i].numpy())
        assert views.covered[i].mean() > 0.5  # neighbouring training frames saw most of its ground
        assert views.background[i].any()  # ground outside the label boxes to score depth on


def test_a_short_fit_scores_finite_numbers_from_twice_the_distance(flight_and_world):
    flight, world = flight_and_world
    dd = load_dynamic_flight(flight)
    train_idx, val_idx = split(dd, 2)
    views = novel_views(flight, dd, train_idx, val_idx, world, scale=2.0, every=3)
    model = fit_dynamic(dd, DynamicFitConfig(kind="kplanes-ext", iters=3, budget_s=None, n_samples=8, batch_rays=128,
                                             max_resolution=32, features=4, hidden=16)).model
    mean, rows, renders = score_novel_views(model, dd, train_idx, views)
    assert [r["frame"] for r in rows] == [dd.data.names[i] for i in views.picked]
    for key in ("novel_psnr", "novel_psnr_covered", "novel_ssim", "depth_rel_median", "depth_off_10pct"):
        assert math.isfinite(mean[key]), key
    # the fit's world is the telemetry's, within the injected noise of the truth's
    assert mean["similarity_scale"] == pytest.approx(1.0, abs=0.05)
    assert all(img.dtype == np.uint8 and img.shape == (48, 64, 3) for img in renders.values())
