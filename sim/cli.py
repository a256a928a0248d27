"""``uavsim sim render``: one simulator view with YOLO labels and a boxes overlay, for a quick look."""

from __future__ import annotations

import logging
import time
from pathlib import Path

log = logging.getLogger(__name__)


def register(subparsers) -> None:
    p = subparsers.add_parser("sim", help="the simulated world")
    sub = p.add_subparsers(dest="sim_command", metavar="SIM_COMMAND")
    sub.required = True
    r = sub.add_parser("render", help="render one view with labels, for a quick look")
    r.add_argument("--altitude", type=float, default=15.0, help="metres above ground")
    r.add_argument("--radius", type=float, default=20.0, help="horizontal distance from the scene centre, m")
    r.add_argument("--pitch", type=float, default=-50.0, help="camera pitch, deg (-90 nadir)")
    r.add_argument("--azimuth", type=float, default=0.0, help="orbit angle, deg counter-clockwise from east")
    r.add_argument("--time", type=float, default=0.0, help="scene time, s (moving people)")
    r.add_argument("--seed", type=int, default=0, help="world seed")
    r.add_argument("--dynamic", action="store_true", help="people walk")
    r.add_argument("--width", type=int, default=640)
    r.add_argument("--height", type=int, default=480)
    r.add_argument("--hfov", type=float, default=70.0, help="horizontal field of view, deg")
    r.add_argument("--supersample", type=int, default=3, help="samples per pixel side")
    r.add_argument("--texture-size", type=int, default=4096,
                   help="ground texture tile side in texels, a power of two (4096: 2.5 cm texels, 102 m tile)")
    r.add_argument("--out", type=Path, required=True, help="output folder")
    r.set_defaults(func=run_render)


def run_render(args) -> int:
    import cv2

    from sim.draw import draw_boxes
    from sim.world import make_world
    from telemetry.camera import Camera, Mount
    from telemetry.frames import orbit_pose

    if not -90.0 <= args.pitch <= 90.0:
        raise ValueError(f"--pitch must be within [-90, 90] deg, got {args.pitch}")
    if args.altitude <= 0.0:
        raise ValueError(f"--altitude must be above the ground (> 0 m), got {args.altitude}")
    if args.width < 8 or args.height < 8:
        raise ValueError(f"image size must be at least 8x8, got {args.width}x{args.height}")
    camera = Camera.from_fov(args.width, args.height, args.hfov, Mount(pitch_deg=args.pitch))
    world = make_world(seed=args.seed, dynamic=args.dynamic, texture_size=args.texture_size,
                       texel_m=0.025 * 4096 / args.texture_size)
    cam_from_world = orbit_pose(args.altitude, args.radius, args.pitch, args.azimuth)
    t0 = time.perf_counter()
    result = world.render(camera, cam_from_world, t=args.time, supersample=args.supersample)
    log.info("rendered %dx%d in %.2f s: %d labelled people", args.width, args.height,
             time.perf_counter() - t0, len(result.boxes))
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out / "view.png"), cv2.cvtColor(result.rgb, cv2.COLOR_RGB2BGR))
    (out / "view.txt").write_text(result.yolo_labels())
    (out / "classes.txt").write_text("".join(n + "\n" for n in world.class_names))
    overlay = draw_boxes(result.rgb, result.boxes, world.class_names)
    cv2.imwrite(str(out / "view_boxes.png"), cv2.cvtColor(overlay, cv2.COLOR_RGB2BGR))
    camera.save(out / "camera.json")
    counts = ", ".join(f"{name}={sum(b.class_id == i for b in result.boxes)}"
                       for i, name in enumerate(world.class_names))
    print(f"{out / 'view.png'}: {len(result.boxes)} people labelled ({counts})")
    return 0
