"""A tiny simulated flight (64x48 px, 8 frames) written in the recorded-flight layout."""

import pytest

from fields.simscene import OrbitSpec, write_orbit_flight
from telemetry.camera import Camera, Mount


@pytest.fixture(scope="session")
def tiny_flight(tmp_path_factory, small_world):
    out = tmp_path_factory.mktemp("flight")
    camera = Camera.from_fov(64, 48, 70.0, Mount(pitch_deg=-45))
    write_orbit_flight(out, small_world, camera, OrbitSpec(15, 20, -45, 8), supersample=1)
    return out
