"""Shared fixtures: small worlds and cameras (tests use images <= 128 px)."""

import pytest

from sim.world import make_world
from telemetry.camera import Camera


@pytest.fixture(scope="session")
def small_world():
    """A deterministic world with a small texture tile (fast to build)."""
    return make_world(seed=3, texture_size=1024, texel_m=0.05)


@pytest.fixture
def small_camera():
    return Camera.from_fov(128, 96, 70.0)
