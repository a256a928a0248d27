import logging

import numpy as np
import pytest

from telemetry.camera import Camera, Mount
from telemetry.frames import cam_from_world_from_attitude, camera_center, euler_zyx_to_matrix, mount_from_cam
from telemetry.geodesy import enu_to_enu_transform
from telemetry.poses import PosesConfig, TelemetryError, extract_tracks, poses_from_telemetry
from telemetry.quat import rotation_angle_deg

from .tlogfactory import ORIGIN, T0, TlogBuilder, factory_flight, heartbeat_gcs, line_position, m, spinning_yaw

CAM = Camera.from_fov(64, 48, 70.0, Mount(pitch_deg=-60.0))


def frame_times(n=15, start_s=0.5, step_s=0.613):
    return [(f"{k:06d}.jpg", T0 + int((start_s + k * step_s) * 1e6)) for k in range(n)]


def errors(poses, frames, camera=CAM, yaw_fn=spinning_yaw, pitch=0.05, roll=-0.04):
    """(position errors m, rotation errors deg) of posed frames against the factory truth."""
    o = poses.origin
    T = enu_to_enu_transform((o.lat, o.lon, o.alt), ORIGIN)
    R_bc = mount_from_cam(camera.mount.roll_deg, camera.mount.pitch_deg, camera.mount.yaw_deg)
    pe, re = [], []
    for e, (_, t) in zip(poses.frames, frames, strict=True):
        if not e.posed:
            continue
        t_s = (t - T0) / 1e6
        truth = cam_from_world_from_attitude(line_position(t_s), euler_zyx_to_matrix(yaw_fn(t_s), pitch, roll), R_bc)
        est = e.cam_from_world @ np.linalg.inv(T)
        pe.append(np.linalg.norm(camera_center(est) - camera_center(truth)))
        re.append(rotation_angle_deg(est[:3, :3], truth[:3, :3]))
    return np.array(pe), np.array(re)


def test_poses_match_truth_with_timesync_and_yaw_wrap():
    b = TlogBuilder()
    factory_flight(b)
    frames = frame_times()
    poses, tracks = poses_from_telemetry(b.records(), frames, CAM)
    assert tracks.time_source == "timesync"
    assert all(e.posed for e in poses.frames)
    pe, re = errors(poses, frames)
    assert np.median(pe) < 0.02 and pe.max() < 0.03  # 1e-7 deg quantisation is ~1 cm
    assert re.max() < 0.05  # yaw crosses ±pi between samples: a naive interpolation would be off by ~180 deg


def test_quaternion_sign_flips_do_not_detour():
    b = TlogBuilder()
    factory_flight(b, quaternion=True)
    frames = frame_times()
    poses, tracks = poses_from_telemetry(b.records(), frames, CAM)
    assert tracks.attitude_message == "ATTITUDE_QUATERNION"
    _, re = errors(poses, frames)
    assert re.max() < 0.05


def test_nadir_camera_pose():
    cam = Camera.from_fov(64, 48, 70.0, Mount(pitch_deg=-90.0))
    b = TlogBuilder()
    factory_flight(b)
    frames = frame_times(5)
    poses, _ = poses_from_telemetry(b.records(), frames, cam)
    pe, re = errors(poses, frames, camera=cam)
    assert re.max() < 0.05 and pe.max() < 0.03
    # optical axis points (almost) straight down in the world
    R = poses.frames[0].cam_from_world[:3, :3]
    z_world = R.T @ np.array([0, 0, 1.0])
    assert z_world[2] < -0.99


def test_system_time_missing_falls_back_with_warning(caplog):
    b = TlogBuilder()
    latency = 30_000
    factory_flight(b, timesync=False, system_time=False, latency_us=latency)
    frames = frame_times(5)
    with caplog.at_level(logging.WARNING):
        poses, tracks = poses_from_telemetry(b.records(), frames, CAM)
    assert tracks.time_source == "receive_time"
    assert any("receive times" in r.message for r in caplog.records)
    assert all(e.posed for e in poses.frames)
    pe, _ = errors(poses, frames)
    # every sample is stamped 30 ms late: at ~5.4 m/s that is ~16 cm, and the fallback cannot know it
    assert 0.1 < np.median(pe) < 0.25


def test_system_time_only_is_used_when_no_timesync():
    b = TlogBuilder()
    factory_flight(b, timesync=False, latency_us=40_000)
    frames = frame_times(5)
    poses, tracks = poses_from_telemetry(b.records(), frames, CAM)
    assert tracks.time_source == "system_time"
    pe, _ = errors(poses, frames)
    assert np.median(pe) < 0.02


def test_frame_before_first_fix_and_after_last_sample_are_unposed():
    b = TlogBuilder()
    factory_flight(b, duration_s=3.0)
    frames = [("a.jpg", T0 - 2_000_000), ("b.jpg", T0 + 1_000_000), ("c.jpg", T0 + 9_000_000)]
    poses, _ = poses_from_telemetry(b.records(), frames, CAM)
    a, bb, c = poses.frames
    assert not a.posed and "before the first position" in a.reason
    assert bb.posed
    assert not c.posed and "after the last" in c.reason


def test_gap_in_telemetry_leaves_frames_unposed_with_reason():
    b = TlogBuilder()
    factory_flight(b, skip=lambda t: 4.0 < t < 5.0)
    frames = [("in_gap.jpg", T0 + 4_500_000), ("ok.jpg", T0 + 2_030_000)]
    poses, tracks = poses_from_telemetry(b.records(), frames, CAM)
    assert not poses.frames[0].posed and "gap" in poses.frames[0].reason
    assert poses.frames[1].posed
    assert tracks.position.gaps(500_000)
    # a larger limit bridges it
    poses2, _ = poses_from_telemetry(b.records(), frames, CAM, PosesConfig(max_gap_s=2.0))
    assert poses2.frames[0].posed


def test_duplicated_and_reordered_messages():
    b = TlogBuilder()
    factory_flight(b)
    rng = np.random.default_rng(0)
    items = list(b.items)
    dup = [items[i] for i in rng.choice(len(items), 40, replace=False)]
    items += dup
    # swap neighbours: receive order no longer follows time_boot_ms
    for i in rng.choice(len(items) - 1, 60, replace=False):
        items[i], items[i + 1] = items[i + 1], items[i]
    b.items = items
    frames = frame_times()
    poses, _ = poses_from_telemetry(b.records(), frames, CAM)
    pe, re = errors(poses, frames)
    assert len(pe) == len(frames)
    assert np.median(pe) < 0.02 and re.max() < 0.05


def test_time_boot_ms_reset_mid_flight():
    """The autopilot reboots at t = 5 s: time_boot_ms restarts near 0; both halves map correctly."""
    b1, b2 = TlogBuilder(), TlogBuilder()
    factory_flight(b1, duration_s=5.0)
    factory_flight(b2, duration_s=5.0, start_us=T0 + 5_500_000, boot_unix_us=T0 + 5_000_000,
                   pos_fn=lambda t: line_position(t + 5.5), yaw_fn=lambda t: spinning_yaw(t + 5.5))
    b1.items += b2.items
    frames = frame_times(16)
    frames = [f for f in frames if not (5.0e6 < f[1] - T0 < 5.6e6)]
    poses, tracks = poses_from_telemetry(b1.records(), frames, CAM)
    assert len(tracks.clock_maps[(1, 1)].epochs) == 2
    assert any("reboot" in w for w in tracks.warnings)
    pe, re = errors(poses, frames)
    assert len(pe) == len(frames)
    assert np.median(pe) < 0.02 and re.max() < 0.05


def test_mixed_systems_mavlink1_and_unknown_messages():
    """Ground-station heartbeats, a companion, a gimbal component of another system, MAVLink 1 frames
    and an unknown message id: poses come only from the autopilot."""
    b = TlogBuilder()
    factory_flight(b, v1=True)  # the autopilot speaks MAVLink 1
    # a GCS (system 255) and a second vehicle (system 7) that must be ignored
    for k in range(10):
        t = T0 + k * 1_000_000
        b.add(t + 5, heartbeat_gcs(), 255, 190)
        b.add(t + 7, m.MAVLink_heartbeat_message(m.MAV_TYPE_ONBOARD_CONTROLLER, m.MAV_AUTOPILOT_INVALID, 0, 0, 4, 3),
              1, 191)
        b.add(t + 9, m.MAVLink_global_position_int_message(k * 1000, 100000000, 100000000, 0, 0, 0, 0, 0, 0), 7, 1)
    data = bytearray(b.data())
    # an unknown message id (a valid MAVLink 2 frame with msgid 0xABCDE) in the middle
    unknown = bytes([0xFD, 1, 0, 0, 3, 1, 1, 0xDE, 0xBC, 0x0A, 0x42, 0x00, 0x00])
    data += (T0 + 500).to_bytes(8, "big") + unknown
    b2 = TlogBuilder()
    factory_flight(b2, duration_s=0.1, start_us=T0 + 20_000_000)
    data += b2.data()
    from telemetry.mavlink import parse_tlog_bytes

    res = parse_tlog_bytes(bytes(data))
    assert res.unknown_ids.get(0xABCDE) == 1
    assert any(r.raw[0] == 0xFE for r in res.records) and any(r.raw[0] == 0xFD for r in res.records)
    frames = frame_times()
    poses, tracks = poses_from_telemetry(res.records, frames, CAM)
    assert tracks.autopilot == (1, 1)
    pe, re = errors(poses, frames)
    assert len(pe) == len(frames) and pe.max() < 0.03


def test_gcs_first_heartbeat_is_not_taken_for_the_autopilot():
    b = TlogBuilder()
    b.add(T0 - 10, heartbeat_gcs(), 255, 190)
    factory_flight(b, duration_s=2.0)
    assert extract_tracks(b.records()).autopilot == (1, 1)


def test_gimbal_follow_mode_overrides_mount():
    b = TlogBuilder()
    factory_flight(b, duration_s=3.0)
    boot0 = T0 - 100_000_000
    q_nadir = [float(np.sqrt(0.5)), 0.0, -float(np.sqrt(0.5)), 0.0]  # pitch -90 about body y
    for k in range(31):
        t = T0 + k * 100_000
        b.add(t + 20_000, m.MAVLink_gimbal_device_attitude_status_message(0, 0, (t - boot0) // 1000, 0, q_nadir,
                                                                          0, 0, 0, 0, 0, 0, 0), 1, 1)
    b.items.sort(key=lambda it: it[0])
    cam = Camera.from_fov(64, 48, 70.0, Mount(pitch_deg=0.0))  # the fixed mount would look at the horizon
    poses, tracks = poses_from_telemetry(b.records(), frame_times(3), cam)
    assert len(tracks.gimbal) == 31
    for e in poses.frames:
        z_world = e.cam_from_world[:3, :3].T @ np.array([0, 0, 1.0])
        assert z_world[2] == pytest.approx(-1.0, abs=1e-6)
    no_gimbal, _ = poses_from_telemetry(b.records(), frame_times(3), cam, PosesConfig(use_gimbal=False))
    z = no_gimbal.frames[0].cam_from_world[:3, :3].T @ np.array([0, 0, 1.0])
    assert abs(z[2]) < 0.1


def test_no_autopilot_or_no_fix_is_a_clear_error():
    b = TlogBuilder()
    b.add(T0, heartbeat_gcs(), 255, 190)
    with pytest.raises(TelemetryError, match="no autopilot"):
        poses_from_telemetry(b.records(), frame_times(2), CAM)
    b.add(T0 + 1, m.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3), 1, 1)
    b.add(T0 + 2, m.MAVLink_global_position_int_message(100, 0, 0, 0, 0, 0, 0, 0, 0), 1, 1)  # lat=lon=0: no fix
    with pytest.raises(TelemetryError, match="no valid GLOBAL_POSITION_INT"):
        poses_from_telemetry(b.records(), frame_times(2), CAM)


def test_mount_status_pitch_overrides_mount():
    b = TlogBuilder()
    factory_flight(b, duration_s=3.0)
    for k in range(31):
        b.add(T0 + k * 100_000 + 20_000, m.MAVLink_mount_status_message(0, 0, -9000, 0, 0, 0), 1, 1)
    b.items.sort(key=lambda it: it[0])
    cam = Camera.from_fov(64, 48, 70.0, Mount(pitch_deg=0.0))
    poses, tracks = poses_from_telemetry(b.records(), frame_times(3), cam)
    assert len(tracks.gimbal) == 31
    for e in poses.frames:
        assert (e.cam_from_world[:3, :3].T @ np.array([0, 0, 1.0]))[2] == pytest.approx(-1.0, abs=1e-6)


def test_nan_attitude_and_zero_quaternion_are_ignored():
    b = TlogBuilder()
    factory_flight(b, duration_s=3.0)
    boot0 = T0 - 100_000_000
    for k in range(5):
        t = T0 + 500_000 + k * 10_000
        b.add(t, m.MAVLink_attitude_message((t - boot0) // 1000, float("nan"), 0.0, float("inf"), 0, 0, 0))
    b.items.sort(key=lambda it: it[0])
    frames = frame_times(4)
    poses, tracks = poses_from_telemetry(b.records(), frames, CAM)
    assert np.isfinite(tracks.attitude.values).all()
    _, re = errors(poses, frames)
    assert len(re) == 4 and re.max() < 0.05
