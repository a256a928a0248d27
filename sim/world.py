"""The simulated world: ground, structures, trees, people and the sun, deterministic by seed.

World coordinates are local ENU metres with the scene centre at the origin and the ground at
z = 0. Scene time ``t`` is in seconds from the start of the scene; only walking people depend on
it. Build one with :func:`make_world` and render it with :meth:`World.render`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from sim.people import CLASS_NAMES, KNEELING, PRONE, STANDING, Clothing, Path2D, Person
from sim.primitives import Primitive, box, capsule, ellipsoid
from sim.texture import GroundTexture, make_ground_texture
from telemetry.frames import rot_z


@dataclass(frozen=True)
class WorldConfig:
    """What :func:`make_world` builds. Distances in metres."""

    seed: int = 0
    n_people: int = 14
    people_radius_m: float = 14.0
    dynamic: bool = False
    #: fraction of people walking in a dynamic scene (the rest keep their pose)
    walking_fraction: float = 0.6
    n_structures: int = 4
    n_trees: int = 8
    texture_size: int = 4096
    texel_m: float = 0.025
    sun_elevation_deg: tuple[float, float] = (35.0, 60.0)
    #: angular radius of the sun disc used for soft shadows (degrees; the real sun is 0.27)
    sun_radius_deg: float = 1.2


@dataclass
class World:
    """Everything the renderer needs. ``scenery`` holds static solids; people move with ``t``."""

    config: WorldConfig
    texture: GroundTexture
    scenery: list[Primitive]
    people: list[Person]
    sun_dir: np.ndarray  # unit vector toward the sun, world ENU
    class_names: tuple[str, ...] = CLASS_NAMES
    extras: dict = field(default_factory=dict)

    def primitives(self, t: float = 0.0) -> list[Primitive]:
        prims = list(self.scenery)
        for person in self.people:
            prims.extend(person.primitives(t))
        return prims

    def person_positions(self, t: float = 0.0) -> np.ndarray:
        """(P, 3) ground positions of the people at time ``t`` (ENU metres, z = 0)."""
        out = np.zeros((len(self.people), 3))
        for i, p in enumerate(self.people):
            out[i, :2] = p.placement(t)[0]
        return out

    def render(self, camera, cam_from_world, t: float = 0.0, supersample: int = 3):
        """Render RGB, instance ids and boxes; see :func:`sim.render.render`."""
        from sim.render import render

        return render(self, camera, cam_from_world, t=t, supersample=supersample)


@lru_cache(maxsize=2)
def _texture(seed: int, size: int, texel_m: float) -> GroundTexture:
    return make_ground_texture(seed, size, texel_m)


def _lin(rgb) -> tuple[float, float, float]:
    return tuple(float((c / 255.0) ** 2.2) for c in rgb)


_SHIRTS = [(40, 60, 110), (150, 30, 30), (200, 200, 190), (60, 90, 50), (30, 30, 30),
           (210, 160, 40), (90, 50, 110), (220, 110, 40), (70, 120, 160), (120, 110, 80)]
_TROUSERS = [(30, 35, 60), (50, 50, 45), (95, 80, 60), (20, 20, 22), (70, 80, 60), (110, 110, 120)]
_SKIN = [(241, 194, 160), (224, 172, 130), (198, 134, 90), (141, 85, 50), (90, 56, 37)]
_HAIR = [(20, 15, 10), (60, 40, 20), (140, 100, 50), (200, 180, 120), (90, 90, 90)]


def _random_clothing(rng: np.random.Generator) -> Clothing:
    def pick(table):
        base = np.asarray(table[rng.integers(len(table))], float)
        return _lin(np.clip(base * rng.uniform(0.85, 1.15), 0, 255))

    return Clothing(pick(_SHIRTS), pick(_TROUSERS), pick(_SKIN), pick(_HAIR),
                    _lin((35, 30, 28)))


def _walking_path(rng: np.random.Generator, start: np.ndarray, radius_m: float) -> Path2D:
    """A smooth closed loop through ``start``: an ellipse with a wobble, walked at 1-1.6 m/s."""
    a, b = rng.uniform(3.0, 7.0, 2)
    rot = rng.uniform(0, 2 * np.pi)
    wobble = rng.uniform(0.05, 0.2)
    phase0 = rng.uniform(0, 2 * np.pi)
    speed = rng.uniform(1.0, 1.6)
    direction = rng.choice([-1.0, 1.0])
    circumference = np.pi * (3 * (a + b) - np.sqrt((3 * a + b) * (a + 3 * b)))
    omega = direction * 2 * np.pi * speed / circumference
    c, s = np.cos(rot), np.sin(rot)
    centre = start - np.array([c * a * np.cos(phase0) - s * b * np.sin(phase0),
                               s * a * np.cos(phase0) + c * b * np.sin(phase0)])
    # keep the loop inside the scene area
    centre *= min(1.0, (radius_m - max(a, b)) / max(np.linalg.norm(centre), 1e-9))

    def position(t: float) -> np.ndarray:
        th = phase0 + omega * t
        r = 1.0 + wobble * np.sin(3 * th)
        x, y = a * r * np.cos(th), b * r * np.sin(th)
        return centre + np.array([c * x - s * y, s * x + c * y])

    return Path2D(position=position, speed_mps=float(speed))


def _place(rng, existing: list[np.ndarray], r_min: float, r_max: float, clearance: float):
    """A random ground point in the annulus [r_min, r_max] at least ``clearance`` from others."""
    for _ in range(200):
        r = np.sqrt(rng.uniform(r_min**2, r_max**2))
        th = rng.uniform(0, 2 * np.pi)
        p = np.array([r * np.cos(th), r * np.sin(th)])
        if all(np.linalg.norm(p - q[:2]) >= clearance + q[2] for q in existing):
            return p
    return None


def make_world(config: WorldConfig | None = None, **overrides) -> World:
    """Build a world from a config (keyword overrides allowed, e.g. ``make_world(seed=3)``)."""
    cfg = config or WorldConfig()
    if overrides:
        cfg = WorldConfig(**{**cfg.__dict__, **overrides})
    rng = np.random.default_rng(cfg.seed)
    texture = _texture(cfg.seed, cfg.texture_size, cfg.texel_m)

    occupied: list[np.ndarray] = []  # (x, y, keep-out radius)
    scenery: list[Primitive] = []

    for _ in range(cfg.n_structures):
        p = _place(rng, occupied, cfg.people_radius_m * 0.6, cfg.people_radius_m + 14.0, 4.0)
        if p is None:
            continue
        length, width = rng.uniform(2.5, 7.0), rng.uniform(2.0, 3.5)
        height = rng.uniform(2.0, 4.5)
        R = rot_z(rng.uniform(0, np.pi))
        wall = _lin(rng.choice([(170, 160, 140), (120, 115, 110), (150, 120, 90), (90, 110, 130)]))
        roof = _lin(rng.choice([(110, 50, 40), (80, 80, 85), (140, 140, 135), (60, 70, 60)]))
        centre = np.array([p[0], p[1], height / 2])
        scenery.append(box(centre, [length / 2, width / 2, height / 2], R, wall))
        scenery.append(box(centre + [0, 0, height / 2 + 0.1],
                           [length / 2 + 0.3, width / 2 + 0.3, 0.1], R, roof))
        occupied.append(np.array([p[0], p[1], 0.5 * np.hypot(length, width) + 1.0]))

    for _ in range(cfg.n_trees):
        p = _place(rng, occupied, cfg.people_radius_m * 0.8, cfg.people_radius_m + 22.0, 2.0)
        if p is None:
            continue
        h = rng.uniform(4.0, 9.0)
        crown_r = rng.uniform(1.5, 3.0)
        trunk_top = h - crown_r * 1.2
        scenery.append(capsule([p[0], p[1], 0.0], [p[0], p[1], trunk_top], 0.15,
                               _lin((80, 60, 40))))
        green = _lin(np.clip(np.array([40, 75, 35]) * rng.uniform(0.8, 1.2), 0, 255))
        scenery.append(ellipsoid([p[0], p[1], trunk_top + crown_r], [crown_r, crown_r,
                                 crown_r * 1.15], rot_z(rng.uniform(0, np.pi)), green))
        occupied.append(np.array([p[0], p[1], crown_r]))

    people: list[Person] = []
    classes = [STANDING, KNEELING, PRONE]
    for k in range(cfg.n_people):
        p = _place(rng, occupied, 0.0, cfg.people_radius_m, 1.6)
        if p is None:
            break
        class_id = classes[k % 3]
        height = {STANDING: rng.uniform(1.65, 1.85), KNEELING: rng.uniform(1.65, 1.85),
                  PRONE: rng.uniform(1.70, 1.85)}[class_id]
        clothing = _random_clothing(rng)
        yaw = rng.uniform(-np.pi, np.pi)
        path = None
        if cfg.dynamic and rng.random() < cfg.walking_fraction:
            class_id = STANDING
            path = _walking_path(rng, p, cfg.people_radius_m)
        people.append(Person(k + 1, class_id, (float(p[0]), float(p[1])), float(yaw),
                             float(height), clothing, path))
        occupied.append(np.array([p[0], p[1], 0.9 if class_id != PRONE else 1.2]))

    elev = np.radians(rng.uniform(*cfg.sun_elevation_deg))
    az = rng.uniform(0, 2 * np.pi)
    sun = np.array([np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev)])
    return World(cfg, texture, scenery, people, sun)


__all__ = ["World", "WorldConfig", "make_world", "CLASS_NAMES", "STANDING", "KNEELING", "PRONE"]
