"""Shared fixtures: small worlds and cameras (tests use images <= 128 px)."""

import os

# Before torch is imported anywhere: spinning OpenMP threads make torch 2-13x slower when another
# process holds a core (measured on these 2-core machines).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# The hash grid's compiled corner kernel (the default) costs seconds to compile per grid shape and
# gains nothing on tests' few steps: tests run eager, except those that switch it on to check it
# equals eager (tests/fields/test_encodings.py). Subprocesses (CLI tests) inherit this.
os.environ.setdefault("UAVSIM_COMPILE", "0")

import pytest  # noqa: E402

from sim.world import make_world  # noqa: E402
from telemetry.camera import Camera  # noqa: E402


@pytest.fixture(scope="session")
def small_world():
    """A deterministic world with a small texture tile (fast to build)."""
    return make_world(seed=3, texture_size=1024, texel_m=0.05)


@pytest.fixture
def small_camera():
    return Camera.from_fov(128, 96, 70.0)
