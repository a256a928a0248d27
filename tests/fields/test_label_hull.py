"""The occupancy cells label boxes vouch for (fields.label_hull) and the sampler's kept cells."""

import numpy as np
import pytest
import torch

from fields.label_hull import vouched_cells
from fields.samplers import OccupancySampler
from telemetry.camera import Camera, Mount
from telemetry.frames import orbit_pose

LO, HI = np.array([-10.0, -10.0, -0.5]), np.array([10.0, 10.0, 5.0])
GRID = (40, 40, 22)  # 0.5 x 0.5 x 0.25 m cells
CAMERA = Camera.from_fov(128, 96, 70.0, Mount(pitch_deg=-45))
#: a standing person's bounding solid (ENU metres): 0.4 x 0.4 m, 1.8 m tall, centred at (2, -1)
PERSON_LO, PERSON_HI = np.array([1.8, -1.2, 0.0]), np.array([2.2, -0.8, 1.8])


def orbit_frames(n: int = 16) -> tuple[list, list]:
    """Poses of a 45-degree orbit at 15 m (radius 15 m) and each frame's label box of the person."""
    corners = np.array([[x, y, z] for x in (PERSON_LO[0], PERSON_HI[0]) for y in (PERSON_LO[1], PERSON_HI[1])
                        for z in (PERSON_LO[2], PERSON_HI[2])])
    poses, boxes = [], []
    for az in np.linspace(0.0, 360.0, n, endpoint=False):
        T = orbit_pose(15.0, 15.0, -45.0, az)
        uv, front = CAMERA.project_world(corners, T)
        assert front.all()
        (x0, y0), (x1, y1) = uv.min(0), uv.max(0)
        poses.append(T)
        boxes.append([(0, x0, y0, x1, y1)] if x0 >= 0 and y0 >= 0 and x1 <= 128 and y1 <= 96 else [])
    assert sum(map(len, boxes)) >= n // 2  # the person is in most frames
    return poses, boxes


def cell_centres(cells: torch.Tensor) -> np.ndarray:
    size = (HI - LO) / np.asarray(GRID)
    return LO + (cells.nonzero().numpy() + 0.5) * size


def cell_of(point) -> tuple:
    return tuple(((np.asarray(point) - LO) / (HI - LO) * np.asarray(GRID)).astype(int))


def test_the_boxes_vouch_for_the_person_and_nothing_far_from_it():
    poses, boxes = orbit_frames()
    cells = vouched_cells(GRID, LO, HI, 0.0, CAMERA, poses, boxes)
    assert cells.shape == GRID and cells.dtype == torch.bool
    assert cells[cell_of([2.1, -0.9, 0.9])]  # the person's middle
    c = cell_centres(cells)
    # every vouched cell lies within one cell of the person's solid
    assert (c[:, :2] > PERSON_LO[:2] - 0.5).all() and (c[:, :2] < PERSON_HI[:2] + 0.5).all(), c
    assert (c[:, 2] < PERSON_HI[2] + 0.5).all() and (c[:, 2] > -0.5).all(), c


def test_frames_that_miss_the_person_do_not_veto_the_others():
    poses, boxes = orbit_frames()
    dropped = [[] if k % 3 == 0 else b for k, b in enumerate(boxes)]  # a third of the labels miss the person
    assert vouched_cells(GRID, LO, HI, 0.0, CAMERA, poses, dropped, min_share=0.5)[cell_of([2.1, -0.9, 0.9])]
    # all labels must agree at min_share 1: one frame without the box is a veto
    assert not vouched_cells(GRID, LO, HI, 0.0, CAMERA, poses, dropped, min_share=1.0).any()


def test_no_boxes_few_views_or_views_that_face_away_vouch_for_nothing():
    poses, boxes = orbit_frames()
    assert not vouched_cells(GRID, LO, HI, 0.0, CAMERA, poses, [[] for _ in poses]).any()
    assert not vouched_cells(GRID, LO, HI, 0.0, CAMERA, poses[:2], boxes[:2], min_views=3).any()
    away = [np.diag([1.0, 1.0, -1.0, 1.0]) @ T for T in poses]  # every camera turned to face up
    assert not vouched_cells(GRID, LO, HI, 0.0, CAMERA, away, boxes).any()


def test_bad_arguments_are_refused():
    poses, boxes = orbit_frames()
    with pytest.raises(ValueError, match="box lists"):
        vouched_cells(GRID, LO, HI, 0.0, CAMERA, poses, boxes[:-1])
    for share, views in ((0.0, 3), (1.5, 3), (float("nan"), 3), (0.5, 0)):
        with pytest.raises(ValueError, match="min_share"):
            vouched_cells(GRID, LO, HI, 0.0, CAMERA, poses, boxes, min_share=share, min_views=views)


def test_kept_cells_are_occupied_and_sampled_whatever_their_density():
    s = OccupancySampler(GRID, n_samples=32, n_coarse=220, update_fraction=1.0)
    lo, hi = torch.tensor(LO, dtype=torch.float32), torch.tensor(HI, dtype=torch.float32)
    s.update(lambda p: torch.zeros(p.shape[0]), lo, hi, full=True)  # the field is empty everywhere
    keep = torch.zeros(GRID, dtype=torch.bool)
    keep[cell_of([2.1, -0.9, 0.0])[:2] + (slice(2, 10),)] = True  # a person's column, z 0 to 2 m
    s.keep_occupied(keep)
    occ = s.occupied(lo, hi)
    assert occ[keep].all() and occ.sum() == 3 * 3 * 10  # dilated by one cell, nothing else
    o, d = torch.tensor([[2.1, -0.9, 15.0]]), torch.tensor([[0.0, 0.0, -1.0]])
    e = s.edges(o, d, lo, hi, train=False)
    z = o[0, 2] - 0.5 * (e[0, 1:] + e[0, :-1])
    assert ((z > -0.3) & (z < 2.3)).sum() >= 24, z  # most of the ray's samples in the person's column

    state = s.state_dict()
    again = OccupancySampler(GRID, n_samples=32, n_coarse=220)
    again.load_state_dict(state)
    assert torch.equal(again.keep, keep) and torch.equal(again.edges(o, d, lo, hi, train=False), e)
    del state["keep"]  # a checkpoint from before kept cells
    again.load_state_dict(state)
    assert again.keep is None and not again.occupied(lo, hi).any()
    with pytest.raises(ValueError, match="do not match"):
        s.keep_occupied(torch.zeros(4, 4, 4, dtype=torch.bool))


def test_a_static_fit_keeps_the_cells_its_labelled_frames_vouch_for(tiny_flight):
    from fields.data import load_flight
    from fields.training import FitConfig, build_model

    d = load_flight(tiny_flight)
    tr, _ = d.split(8)
    cfg = FitConfig(iters=1, budget_s=None, n_samples=16, budget_mb=1.0, threads=1, occupancy_keep_share=0.5)
    model, _, sizing = build_model(d, tr, cfg, None)
    assert model.sampler.keep is not None and 0 < int(model.sampler.keep.sum()) < model.sampler.keep.numel() // 100
    assert any("stay occupied" in r for r in sizing.reasoning)
    off, _, _ = build_model(d, tr, FitConfig(**{**cfg.__dict__, "occupancy_keep_share": None}), None)
    assert off.sampler.keep is None
