"""The capacity bench's walkers stay where the encoding can fit them; the fit runs end to end."""

import math

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from bench import kplanes_capacity as kc


@settings(max_examples=40, deadline=None)
@given(n=st.integers(1, 32), seed=st.integers(0, 2**31 - 1))
def test_every_walker_stays_inside_the_square_for_the_whole_walk(n, seed):
    # Session 30's bench let walkers leave the 40 m square; the encoding clamps such points to its border,
    # so those walkers could not be fitted and four walkers scored ~4 dB lower than they fit.
    p0, v, colour = kc.walkers(n, torch.Generator().manual_seed(seed))
    times = torch.arange(kc.INSTANTS, dtype=torch.float32) * kc.DT_S
    pos = p0[None] + v[None] * times[:, None, None]
    assert float(pos.abs().max()) + kc.RADIUS_M < kc.SIDE_M / 2
    assert torch.allclose(v.norm(dim=1), torch.full((n,), kc.SPEED_M_S))
    assert bool(((colour >= 0) & (colour <= 1)).all())


def test_truth_marks_a_walker_and_leaves_the_ground_grey():
    people = kc.walkers(1, torch.Generator().manual_seed(0))
    p0, _, colour = people
    xy = torch.stack([p0[0], p0[0] + torch.tensor([5.0, 0.0])])
    out = kc.truth(xy, torch.zeros(2, dtype=torch.long), people, one_at_a_time=False)
    assert torch.allclose(out[0], torch.cat([colour[0], torch.ones(1)]))
    assert torch.allclose(out[1], torch.tensor([kc.GROUND_RGB] * 3 + [0.0]))


def test_a_short_fit_scores_finite_numbers_with_every_option():
    row = kc.fit_and_score(2, steps=3, near_div=2, one_at_a_time=True, seed=1, features=4, hidden=8,
                           xyt_hash_log2=10, flight_times=True, same_colour=True)
    assert math.isfinite(row["colour_psnr_db"]) and 0.0 <= row["occupancy_iou"] <= 1.0
    assert math.isfinite(row["between_colour_psnr_db"]) and 0.0 <= row["between_occupancy_iou"] <= 1.0
    assert row["xyt_hash_log2"] == 10 and row["same_colour"] and row["flight_times"]


def test_truth_between_instants_puts_the_walker_halfway():
    people = kc.walkers(1, torch.Generator().manual_seed(3))
    p0, v, _ = people
    halfway = p0[0] + v[0] * 0.5 * kc.DT_S
    out = kc.truth(halfway[None], torch.tensor([0.5]), people, one_at_a_time=True)
    assert float(out[0, 3]) == 1.0
