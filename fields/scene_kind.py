"""``--kind auto``: does a flight need a dynamic field? Model only what the scene needs.

Evidence: labelled people whose ground positions move over time. Each label box's bottom centre
(the feet of a standing person) is cast through the frame's pose onto the ground plane
``z = ground_z`` (world ENU metres). A person seen in frame i counts as "moved" when, in every
other labelled frame at least ``min_gap_s`` away in time that should show that spot (inside the
image, and near enough that a person there would be as large as the 10 % smallest labelled
people), nobody is within ``move_threshold_m``. Occlusions, missed labels and pose noise make
people look moved in static scenes too, so the same fraction over frames at most ``short_gap_s``
away (walkers move < 1 m) is the baseline: the scene is dynamic when the long-gap fraction exceeds
the short-gap one by at least ``min_excess`` (with at least ``min_observations`` long-gap
observations). Without labels, with a single frame or a flight shorter than ``min_gap_s`` there is
no evidence of motion: static. (The other possible test — the residual of a quick static fit
concentrated on people — is not implemented.)
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field

import numpy as np

log = logging.getLogger(__name__)


@dataclass
class KindOptions:
    move_threshold_m: float = 2.0
    min_gap_s: float = 3.0
    short_gap_s: float = 0.6
    min_excess: float = 0.15
    min_observations: int = 5
    #: a projected point must lie this fraction of the image size inside the later frame
    margin: float = 0.05


@dataclass
class KindChoice:
    kind: str  # "static" or "dynamic"
    reason: str
    evidence: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        return asdict(self)


def ground_points(camera, cam_from_world: np.ndarray, boxes: list[tuple], ground_z: float = 0.0) -> np.ndarray:
    """(K, 2) ENU ground points of the boxes' bottom centres; boxes whose ray does not go down are dropped.
    ``boxes``: [(class, x0, y0, x1, y1)] in pixel edges."""
    if not boxes:
        return np.zeros((0, 2))
    uv = np.array([[(b[1] + b[3]) / 2.0, b[4]] for b in boxes], dtype=np.float64)
    uv[:, 1] = np.minimum(uv[:, 1], camera.height - 0.5)
    o, d = camera.rays_world(np.asarray(cam_from_world, np.float64), uv)
    o = np.broadcast_to(o, d.shape)
    down = d[:, 2] < -1e-6
    t = np.where(down, (ground_z - o[:, 2]) / np.where(down, d[:, 2], -1.0), np.nan)
    p = o + t[:, None] * d
    return p[down & np.isfinite(t) & (t > 0), :2]


def person_px(camera, cam_from_world, pts_xy: np.ndarray, ground_z: float, height_m: float = 1.7) -> np.ndarray:
    """Apparent size (pixels, focal length x height / range) of a person standing at ground points."""
    T = np.asarray(cam_from_world, np.float64)
    centre = -T[:3, :3].T @ T[:3, 3]
    pts = np.column_stack([pts_xy, np.full(len(pts_xy), ground_z)])
    rng = np.linalg.norm(pts - centre, axis=1)
    return 0.5 * (camera.fx + camera.fy) * height_m / np.maximum(rng, 1e-6)


def _in_view(camera, cam_from_world, pts_xy: np.ndarray, ground_z: float, margin: float, min_px: float) -> np.ndarray:
    """Ground points inside the image (with a margin) and near enough that a person there gets a label."""
    pts = np.column_stack([pts_xy, np.full(len(pts_xy), ground_z)])
    uv, front = camera.project_world(pts, cam_from_world)
    mx, my = margin * camera.width, margin * camera.height
    inside = front & (uv[:, 0] >= mx) & (uv[:, 0] <= camera.width - mx) & (uv[:, 1] >= my) & \
        (uv[:, 1] <= camera.height - my)
    return inside & (person_px(camera, cam_from_world, pts_xy, ground_z) >= min_px)


def _finite_median(values: list[float]) -> float | None:
    v = [x for x in values if np.isfinite(x)]
    return round(float(np.median(v)), 2) if v else None


def choose_kind(camera, cam_from_world: list[np.ndarray], times_us: np.ndarray, boxes: list[list[tuple]] | None,
                has_labels: list[bool] | None = None, ground_z: float = 0.0,
                options: KindOptions | None = None) -> KindChoice:
    """Static or dynamic from moving labels (see the module docstring). ``boxes[i]`` are frame i's
    label boxes; ``has_labels[i]`` False means frame i has no label file (no evidence either way)."""
    opt = options or KindOptions()
    n = len(cam_from_world)
    times = np.asarray(times_us, dtype=np.int64)
    if n != len(times) or (boxes is not None and len(boxes) != n):
        raise ValueError("poses, times and boxes must have one entry per frame")
    labelled = [i for i in range(n) if boxes is not None and (has_labels is None or has_labels[i])]
    span_s = float(times.max() - times.min()) / 1e6 if n else 0.0
    ev = {"frames": n, "labelled_frames": len(labelled), "span_s": round(span_s, 2),
          "options": asdict(opt)}
    if n < 2:
        return KindChoice("static", "a single frame: nothing can be seen to move", ev)
    if not labelled:
        return KindChoice("static", "no labels: no evidence that anything moves", ev)
    if span_s < opt.min_gap_s:
        return KindChoice("static", f"the flight lasts {span_s:.1f} s (< {opt.min_gap_s:g} s): too short to see "
                          "people move", ev)
    pts = {i: ground_points(camera, cam_from_world[i], boxes[i], ground_z) for i in labelled}
    # the smallest person the labels still show (10th pct of the labelled people's apparent size):
    # people farther away in another frame are not expected to be labelled there
    sizes = np.concatenate([person_px(camera, cam_from_world[i], pts[i], ground_z) for i in labelled] or [[]])
    min_px = float(np.percentile(sizes, 10)) if len(sizes) else 0.0
    ev["min_person_px"] = round(min_px, 1)
    in_view = {(i, j): _in_view(camera, cam_from_world[j], pts[i], ground_z, opt.margin, min_px)
               for i in labelled for j in labelled if i != j and len(pts[i])}

    def moved_fraction(near: bool):
        """Over labelled people: is anyone within the threshold in the frames at the given time gap?"""
        moved = total = 0
        dists = []
        for i in labelled:
            if not len(pts[i]):
                continue
            best = np.full(len(pts[i]), np.inf)
            seen = np.zeros(len(pts[i]), bool)
            for j in labelled:
                if j == i:
                    continue
                gap = abs(int(times[j]) - int(times[i])) / 1e6
                if (gap > opt.short_gap_s) if near else (gap < opt.min_gap_s):
                    continue
                ok = in_view[(i, j)]
                seen |= ok
                if len(pts[j]) and ok.any():
                    d = np.linalg.norm(pts[i][:, None, :] - pts[j][None, :, :], axis=-1).min(axis=1)
                    best = np.where(ok, np.minimum(best, d), best)
            dists += best[seen].tolist()
            moved += int((best[seen] > opt.move_threshold_m).sum())
            total += int(seen.sum())
        return (moved / total if total else None), total, dists

    f_long, n_long, d_long = moved_fraction(near=False)
    f_short, n_short, _ = moved_fraction(near=True)
    gaps = [abs(int(times[j]) - int(times[i])) / 1e6 for a, i in enumerate(labelled) for j in labelled[a + 1:]]
    n_long_pairs = sum(g >= opt.min_gap_s for g in gaps)
    n_short_pairs = sum(g <= opt.short_gap_s for g in gaps)
    excess = None if f_long is None else f_long - (f_short or 0.0)
    ev.update(long_gap_pairs=n_long_pairs, long_gap_observations=n_long,
              moved_fraction_long_gap=None if f_long is None else round(f_long, 3),
              short_gap_pairs=n_short_pairs, short_gap_observations=n_short,
              moved_fraction_short_gap=None if f_short is None else round(f_short, 3),
              excess=None if excess is None else round(excess, 3),
              median_nearest_m_long_gap=_finite_median(d_long))
    if f_long is None or n_long < opt.min_observations:
        return KindChoice("static", f"only {n_long} observations of the same ground {opt.min_gap_s:g} s apart: "
                          "no evidence of motion", ev)
    if excess >= opt.min_excess:
        return KindChoice("dynamic", f"{100 * f_long:.0f} % of labelled people have nobody within "
                          f"{opt.move_threshold_m:g} m >= {opt.min_gap_s:g} s earlier or later "
                          f"(vs {100 * (f_short or 0):.0f} % within {opt.short_gap_s:g} s): people move", ev)
    return KindChoice("static", f"labelled people stay put: {100 * f_long:.0f} % look moved after >= "
                      f"{opt.min_gap_s:g} s (vs {100 * (f_short or 0):.0f} % within {opt.short_gap_s:g} s; "
                      f"threshold +{100 * opt.min_excess:.0f} %)", ev)
