"""What PSNR at 35 / 50 m the 15 m orbit's data allows: an oracle that knows the ground as sharply as
the sharpest training frame saw it.

``bench/fields.py`` scores renders of a field fitted to the 15 m orbit against simulator truth at
35 m and 50 m. Those views see ground the orbit saw only from far off, at grazing angles, or not at
all. No field can render that ground sharper than the data showed it, so this script asks what the
best possible render scores: for each pixel of a truth view (at the bench's evaluation resolution,
160x120), the ground point (ENU z = 0) it sees, the ground footprint of one pixel there in the view
(``g_view``) and in each 320x240 training frame that sees the point (``g_train``, the finest over
frames), both as the side of a square of the same area, metres: ``range / f / sqrt(cos incidence)``
(``--longest``: the footprint's long axis, ``range / f / cos incidence``).
The oracle pixel is the truth image low-passed to ``max(1, g_train / g_view)`` pixels (area
downsampling and bilinear upsampling, in octave steps of sqrt(2)); a pixel whose ground no training
frame saw gets the truth image's mean colour. Where pixels were seen the oracle is generous: it
ignores pose and photometric error, takes the single sharpest view's resolution everywhere and (without
``--occlusion``) ignores heights. Where they were not, the mean colour is a plain guess that a field
filling the gap from its surroundings could beat. So its PSNR says what the data supports, roughly; it
is not a result any field reached.

``--model PATH`` (a checkpoint ``bench/fields.py`` saved, e.g. ``bench/out/fields_hash-occ32.pt``) also
scores that field's renders, and both the field and the oracle by region of the ground: under the
orbit (<= 20 m from the centre), inside the field's box beyond the orbit, outside the box (the
cheap background).

``--occlusion`` makes the oracle honest about heights: the surface is the first hit with the ground or a
tree or structure of the simulator world, and a training frame sees it only when nothing solid stands
between (the far ground, seen from the other side of the orbit at grazing angles, hides behind trees).

    python bench/fields_ceiling.py [--occlusion] [--longest] [--model bench/out/fields_hash-occ32.pt] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from bench._common import OUT_DIR, write_json  # noqa: E402
from bench.fields import ALTITUDE_VIEWS, half, in_frame, orbit_mask, prepare, rays_to_ground  # noqa: E402


def footprint_m(range_m, cos_incidence, focal_px: float, longest: bool = False):
    """Ground footprint of one pixel (m) at ``range_m`` and incidence ``cos_incidence`` (to the vertical):
    the side of the equal-area square ``range / f / sqrt(cos)``, or with ``longest`` its long axis along
    the view ``range / f / cos`` (foreshortening)."""
    return range_m / focal_px / (cos_incidence if longest else np.sqrt(cos_incidence))


def ground_hits(camera, cam_from_world: np.ndarray, longest: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel of ``camera``: the ground point (ENU, z = 0; (H*W, 3), NaN where the ray does not
    come down) and the pixel's ground footprint there (m; :func:`footprint_m`)."""
    o, d, t = rays_to_ground(camera, cam_from_world)
    t = np.where(np.isfinite(t), t, np.nan)
    f = 0.5 * (camera.fx + camera.fy)
    return o + t[:, None] * d, footprint_m(t, np.abs(d[:, 2]), f, longest)


def finest_training_footprint(camera, train_Ts: list[np.ndarray], pts: np.ndarray, longest: bool = False
                              ) -> np.ndarray:
    """(N,) the finest ground footprint (m, :func:`footprint_m`) at which any training frame sees each
    ground point (inf: none)."""
    f = 0.5 * (camera.fx + camera.fy)
    best = np.full(len(pts), np.inf)
    ok_pts = np.isfinite(pts).all(1)
    for T in train_Ts:
        inside = ok_pts & in_frame(camera, *camera.project_world(np.where(ok_pts[:, None], pts, 0.0), T))
        centre = -T[:3, :3].T @ T[:3, 3]
        v = centre[None, :] - pts
        rng = np.linalg.norm(v, axis=1)
        cos_inc = np.clip(v[:, 2] / np.maximum(rng, 1e-9), 1e-6, 1.0)
        g = footprint_m(rng, cos_inc, f, longest)
        best = np.where(inside & (g < best), g, best)
    return best


def visible_from_training(world, camera, train_Ts: list[np.ndarray], view_T: np.ndarray, g_train: np.ndarray,
                          view_camera) -> np.ndarray:
    """``--occlusion``: ``g_train`` (N,) with inf where no training frame sees the surface the view's pixel
    sees. The surface point is the view ray's first hit with the ground or a static solid of ``world``
    (trees, structures; people are too small to matter); a training frame sees it when it projects into
    the frame and no solid lies on the segment from the camera centre to it (convex solids: a back face
    counts as hidden by its own front). Footprints stay the ground's (:func:`footprint_m`)."""
    from sim.primitives import intersect

    o, d, t = rays_to_ground(view_camera, view_T)
    for prim in world.scenery:
        t = np.minimum(t, intersect(prim, o, d, 1e-4))
    surf = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
    out = np.where(np.isfinite(t), g_train, np.inf)
    seen = np.zeros(len(surf), bool)
    for T in train_Ts:
        inside = in_frame(camera, *camera.project_world(surf, T))
        centre = np.broadcast_to(-T[:3, :3].T @ T[:3, 3], surf.shape)
        v = surf - centre
        dist = np.linalg.norm(v, axis=1)
        u = v / np.maximum(dist, 1e-9)[:, None]
        clear = inside.copy()
        for prim in world.scenery:
            clear &= ~(intersect(prim, centre, u, 1e-4) < dist - 1e-3)
        seen |= clear
    return np.where(seen, out, np.inf)


def oracle_image(truth: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """``truth`` (H, W, 3) uint8 low-passed per pixel to ``scale`` (H, W) pixels (>= 1; inf: unseen,
    the image's mean colour), in sqrt(2) octave steps; float in [0, 1]."""
    import cv2

    img = truth.astype(np.float32) / 255.0
    h, w = img.shape[:2]
    out = np.empty_like(img)
    mean = img.reshape(-1, 3).mean(0)
    level = np.where(np.isfinite(scale), np.round(2 * np.log2(np.maximum(scale, 1.0))), -1).astype(int)
    for lv in np.unique(level):
        sel = level == lv
        if lv < 0:
            out[sel] = mean
            continue
        s = 2.0 ** (lv / 2)
        small = cv2.resize(img, (max(1, round(w / s)), max(1, round(h / s))), interpolation=cv2.INTER_AREA)
        out[sel] = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)[sel]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--flight", type=Path, default=OUT_DIR / "fields_flight")
    ap.add_argument("--model", type=Path, default=None, help="a saved field to score by region too")
    ap.add_argument("--occlusion", action="store_true",
                    help="a pixel counts as seen only where a training frame sees its surface unoccluded by the "
                         "world's trees and structures (needs the simulator world)")
    ap.add_argument("--longest", action="store_true",
                    help="footprints by their long axis (foreshortened along the view), not their area: a "
                         "stricter oracle")
    ap.add_argument("--regions-from", type=Path, default=None,
                    help="take the box that splits the regions from this saved field instead of --model's "
                         "(to compare fields whose boxes differ on the same pixels)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()

    from fields.data import load_flight
    from fields.evaluation import psnr

    camera, views = prepare(args.flight)
    data = load_flight(args.flight)
    train_idx, _ = data.split(8)
    train_Ts = [data.cam_from_world[i] for i in train_idx]
    cam_half = camera.scaled(0.5)
    model = None
    if args.model:
        from fields.training import load_checkpoint

        model, _ = load_checkpoint(args.model, "cpu")
        model.eval()
        lo, hi = model.field.lo.numpy(), model.field.hi.numpy()
        if args.regions_from:
            ref, _ = load_checkpoint(args.regions_from, "cpu")
            lo, hi = ref.field.lo.numpy(), ref.field.hi.numpy()
    world = None
    if args.occlusion:
        from sim.world import make_world

        world = make_world(seed=0)
    rows = []
    for alt, az, T, rgb in views:
        truth = half(rgb)
        pts, g_view = ground_hits(cam_half, T, args.longest)
        g_train = finest_training_footprint(camera, train_Ts, pts, args.longest)
        if world is not None:
            g_train = visible_from_training(world, camera, train_Ts, T, g_train, cam_half)
        scale = (g_train / g_view).reshape(truth.shape[:2])
        oracle = oracle_image(truth, scale)
        orbit = half(orbit_mask(camera, T).astype(np.float32)) > 0.5
        seen = np.isfinite(scale)
        rows.append({"altitude_m": alt, "azimuth_deg": az, "oracle_psnr": psnr(oracle, truth),
                     "oracle_psnr_orbit": psnr(oracle, truth, orbit),
                     "unseen_fraction": float(1 - seen.mean()),
                     "median_blur_px": float(np.median(np.maximum(scale[seen], 1.0))),
                     "blur_over_2px_fraction": float((scale > 2).mean())})
        if model is not None:
            g = pts[:, :2].reshape(*truth.shape[:2], 2)
            in_box = np.isfinite(g).all(-1) & (g >= lo[:2]).all(-1) & (g <= hi[:2]).all(-1)
            regions = {"orbit": orbit, "box_beyond_orbit": in_box & ~orbit, "outside_box": ~in_box}
            render = model.render_image(cam_half, T, with_mask=False)["rgb"]
            rows[-1]["field_psnr"] = psnr(render, truth)
            rows[-1]["field_psnr_seen"] = psnr(render, truth, seen)  # what the field could know
            for name, sel in regions.items():
                rows[-1][f"share_{name}"] = float(sel.mean())
                rows[-1][f"field_psnr_{name}"] = psnr(render, truth, sel)
                rows[-1][f"oracle_psnr_{name}"] = psnr(oracle, truth, sel)
        print(json.dumps({k: round(v, 3) if isinstance(v, float) else v for k, v in rows[-1].items()}), flush=True)
    summary = {}
    for alt in ALTITUDE_VIEWS:
        sel = [r for r in rows if r["altitude_m"] == alt]
        summary[str(alt)] = {k: round(float(np.nanmean([r[k] for r in sel])), 3) for k in sel[0]
                             if k not in ("altitude_m", "azimuth_deg")}
    print(json.dumps(summary), flush=True)
    write_json("fields_ceiling", {"views": rows, "mean_by_altitude": summary}, args.json)


if __name__ == "__main__":
    main()
