"""People as articulated solids in three poses (standing, kneeling, prone), optionally walking.

A person is a skeleton of joints in a body frame (x forward, y left, z up, metres, feet on the
ground at the origin) scaled by the person's height, dressed in capsules and ellipsoids. Class ids
follow the recorded-flight default ``classes.txt``: 0 standing, 1 kneeling, 2 prone.
Heights: standing ~1.75 m, kneeling ~1.0 m, prone ~0.4 m high and ~1.8 m long.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from sim.primitives import Primitive, capsule, ellipsoid
from telemetry.frames import rot_y, rot_z

CLASS_NAMES = ("standing", "kneeling", "prone")
STANDING, KNEELING, PRONE = 0, 1, 2

#: Reference stature the joint tables below are written for (metres).
_REF_HEIGHT = 1.75


@dataclass(frozen=True)
class Clothing:
    """Linear-RGB albedos of a person's parts."""

    shirt: tuple[float, float, float]
    trousers: tuple[float, float, float]
    skin: tuple[float, float, float]
    hair: tuple[float, float, float]
    shoes: tuple[float, float, float]


@dataclass(frozen=True)
class Path2D:
    """A walking path: position (x, y) in ENU metres and heading as functions of time (s)."""

    position: Callable[[float], np.ndarray]
    speed_mps: float


@dataclass(frozen=True)
class Person:
    """One person instance (``instance`` >= 1) with a pose class and placement.

    ``yaw_rad`` is the heading of the body x axis, counter-clockwise from east (ENU).
    A person with a ``path`` walks (class standing) and ignores ``position``/``yaw_rad``.
    """

    instance: int
    class_id: int
    position: tuple[float, float]
    yaw_rad: float
    height_m: float
    clothing: Clothing
    path: Path2D | None = None

    def placement(self, t: float) -> tuple[np.ndarray, float, float]:
        """World (x, y), yaw (rad) and gait phase (rad) at scene time ``t`` seconds."""
        if self.path is None:
            return np.asarray(self.position, float), self.yaw_rad, 0.0
        p = self.path.position(t)
        dt = 0.05
        ahead = self.path.position(t + dt) - self.path.position(t - dt)
        yaw = float(np.arctan2(ahead[1], ahead[0])) if np.linalg.norm(ahead) > 1e-9 else 0.0
        stride_m = 1.45 * self.height_m / _REF_HEIGHT
        phase = 2.0 * np.pi * self.path.speed_mps * t / stride_m
        return p, yaw, phase

    def primitives(self, t: float = 0.0) -> list[Primitive]:
        """The solids of this person at scene time ``t`` in world coordinates."""
        xy, yaw, phase = self.placement(t)
        s = self.height_m / _REF_HEIGHT
        parts = _SKELETONS[self.class_id](phase if self.path is not None else None)
        R = rot_z(yaw)
        origin = np.array([xy[0], xy[1], 0.0])
        c = self.clothing
        colours = {"shirt": c.shirt, "trousers": c.trousers, "skin": c.skin, "hair": c.hair,
                   "shoes": c.shoes}
        out: list[Primitive] = []
        for part in parts:
            albedo = colours[part[1]]
            if part[0] == "capsule":
                _, _, a, b, r = part
                out.append(capsule(origin + R @ (s * np.asarray(a)), origin + R @ (s * np.asarray(b)),
                                   s * r, albedo, self.instance))
            else:
                _, _, center, radii, R_local = part
                out.append(ellipsoid(origin + R @ (s * np.asarray(center)), s * np.asarray(radii),
                                     R @ R_local, albedo, self.instance))
        return out


def _limb(name, a, b, r):
    return ("capsule", name, np.asarray(a, float), np.asarray(b, float), r)


def _blob(name, center, radii, R=None):
    return ("ellipsoid", name, np.asarray(center, float), np.asarray(radii, float),
            np.eye(3) if R is None else R)


def _upper_body(hip_z: float, lean_rad: float, hip_x: float = 0.0, arms: str = "down",
                arm_swing: float = 0.0):
    """Pelvis, torso, head and arms above a hip point, the torso leaning forward by ``lean``."""
    R_lean = rot_y(lean_rad)  # rotating +z toward +x for positive lean
    hip = np.array([hip_x, 0.0, hip_z])

    def up(v):
        return hip + R_lean @ np.asarray(v, float)

    parts = [
        _blob("trousers", up([0, 0, 0.06]), [0.11, 0.17, 0.12], R_lean),
        _blob("shirt", up([0, 0, 0.30]), [0.12, 0.19, 0.26], R_lean),
        _blob("skin", up([0.01, 0, 0.66]), [0.095, 0.085, 0.11], R_lean),
        _blob("hair", up([-0.015, 0, 0.72]), [0.09, 0.085, 0.085], R_lean),
    ]
    for side in (1.0, -1.0):
        shoulder = up([0.0, side * 0.19, 0.50])
        if arms == "down":
            swing = side * arm_swing
            elbow = shoulder + R_lean @ np.array([0.30 * np.sin(swing), side * 0.04,
                                                  -0.30 * np.cos(swing)])
            wrist = elbow + R_lean @ np.array([0.27 * np.sin(swing + 0.25), side * 0.01,
                                               -0.27 * np.cos(swing + 0.25)])
        elif arms == "aim":  # both hands forward at chest height, as when holding something
            elbow = shoulder + np.array([0.22, -side * 0.05, -0.18])
            wrist = elbow + np.array([0.26, -side * 0.10, 0.05])
        else:  # "forward": prone, forearms on the ground in front of the head
            elbow = shoulder + np.array([0.22, side * 0.08, -0.08])
            wrist = elbow + np.array([0.26, -side * 0.06, 0.0])
        parts.append(_limb("shirt", shoulder, elbow, 0.048))
        parts.append(_limb("skin", elbow, wrist, 0.038))
    return parts


def _standing(phase: float | None):
    swing = 0.0 if phase is None else 0.45 * np.sin(phase)
    parts = []
    for side, sgn in ((1.0, 1.0), (-1.0, -1.0)):
        a = sgn * swing
        hip = np.array([0.0, side * 0.095, 0.93])
        knee_bend = 0.0 if phase is None else max(0.0, 0.6 * np.sin(phase * sgn + 1.2))
        knee = hip + np.array([0.45 * np.sin(a), 0.0, -0.45 * np.cos(a)])
        shin_angle = a - knee_bend
        ankle = knee + np.array([0.42 * np.sin(shin_angle), 0.0, -0.42 * np.cos(shin_angle)])
        ankle[2] = max(ankle[2], 0.07)
        parts.append(_limb("trousers", hip, knee, 0.075))
        parts.append(_limb("trousers", knee, ankle, 0.058))
        parts.append(_limb("shoes", ankle, ankle + np.array([0.17, 0.0, -0.02]), 0.045))
    return parts + _upper_body(0.93, 0.03, arms="down", arm_swing=-swing * 0.8)


def _kneeling(phase: float | None):
    # Right knee on the ground, sitting back toward the right heel; left foot planted in front.
    hip_r, hip_l = np.array([0.0, -0.095, 0.34]), np.array([0.0, 0.095, 0.34])
    knee_r = np.array([0.12, -0.12, 0.06])
    ankle_r = np.array([-0.30, -0.12, 0.07])
    knee_l = np.array([0.42, 0.12, 0.45])
    ankle_l = np.array([0.42, 0.12, 0.07])
    parts = [
        _limb("trousers", hip_r, knee_r, 0.075),
        _limb("trousers", knee_r, ankle_r, 0.058),
        _limb("shoes", ankle_r, ankle_r + np.array([-0.14, 0.0, -0.02]), 0.045),
        _limb("trousers", hip_l, knee_l, 0.075),
        _limb("trousers", knee_l, ankle_l, 0.058),
        _limb("shoes", ankle_l, ankle_l + np.array([0.17, 0.0, -0.02]), 0.045),
    ]
    return parts + _upper_body(0.34, 0.50, arms="aim")


def _prone(phase: float | None):
    # Lying face down along +x: body axis horizontal, head slightly raised, legs apart.
    R_flat = rot_y(np.pi / 2)  # body "up" (z) becomes forward (+x)
    hip = np.array([0.0, 0.0, 0.14])

    def at(v):
        return hip + R_flat @ np.asarray(v, float)

    parts = [
        _blob("trousers", at([0, 0, 0.06]), [0.11, 0.17, 0.13], R_flat),
        _blob("shirt", at([0, 0, 0.31]), [0.12, 0.20, 0.26], R_flat),
        _blob("skin", at([-0.12, 0, 0.66]), [0.095, 0.085, 0.11], R_flat),
        _blob("hair", at([-0.14, 0, 0.68]), [0.09, 0.085, 0.085], R_flat),
    ]
    for side in (1.0, -1.0):
        h = np.array([0.0, side * 0.10, 0.13])
        knee = np.array([-0.45, side * 0.20, 0.09])
        ankle = np.array([-0.86, side * 0.28, 0.10])
        parts += [
            _limb("trousers", h, knee, 0.075),
            _limb("trousers", knee, ankle, 0.058),
            _limb("shoes", ankle, ankle + np.array([-0.05, 0.0, 0.12]), 0.045),
        ]
        shoulder = np.array([0.50, side * 0.20, 0.16])
        elbow = np.array([0.68, side * 0.30, 0.06])
        wrist = np.array([0.90, side * 0.12, 0.06])
        parts += [_limb("shirt", shoulder, elbow, 0.048), _limb("skin", elbow, wrist, 0.038)]
    return parts


_SKELETONS = {STANDING: _standing, KNEELING: _kneeling, PRONE: _prone}
