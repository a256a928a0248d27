"""Rotations and reference frames shared by the whole project.

Conventions (see DESIGN.md §3):
- world: local ENU, metres (x east, y north, z up).
- MAVLink attitude: NED navigation frame, FRD body frame, Z-Y-X Euler angles (yaw, pitch, roll) in radians.
- camera: OpenCV (x right, y down, z forward). Poses are stored as ``cam_from_world`` 4x4 matrices,
  i.e. ``p_cam = R @ p_world + t``.
- camera mount: Z-Y-X Euler angles of the camera boresight relative to the body FRD frame; all zero
  looks straight forward with image x along body right and image y along body down; pitch -90 deg is nadir.

All functions are numpy float64 and free of global state.
"""

from __future__ import annotations

import numpy as np

#: Rotation taking NED vectors to ENU vectors (its own inverse).
R_ENU_FROM_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])

#: Rotation taking OpenCV camera vectors to the camera mount frame (FRD-like, x along the boresight).
R_MOUNT_FROM_CAM = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def rot_x(angle_rad: float) -> np.ndarray:
    """Active rotation about x by ``angle_rad`` (right-handed)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle_rad: float) -> np.ndarray:
    """Active rotation about y by ``angle_rad`` (right-handed)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle_rad: float) -> np.ndarray:
    """Active rotation about z by ``angle_rad`` (right-handed)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def euler_zyx_to_matrix(yaw_rad: float, pitch_rad: float, roll_rad: float) -> np.ndarray:
    """``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``: the aerospace Z-Y-X convention.

    For MAVLink ATTITUDE this is ``R_ned_from_body`` (FRD body).
    """
    return rot_z(yaw_rad) @ rot_y(pitch_rad) @ rot_x(roll_rad)


def matrix_to_euler_zyx(R: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`euler_zyx_to_matrix`: (yaw, pitch, roll) in radians.

    At the pitch = ±90 deg singularity yaw and roll are not separable; roll is set to 0 and the
    whole rotation about the vertical goes into yaw, so the result still reproduces ``R``.
    """
    R = np.asarray(R, dtype=np.float64)
    sp = -R[2, 0]
    sp = float(np.clip(sp, -1.0, 1.0))
    pitch = float(np.arcsin(sp))
    if abs(sp) > 1.0 - 1e-9:
        roll = 0.0
        # R = Rz(yaw) Ry(±90): first row gives -sin(yaw) in [0,1] and cos(yaw) in [1,1].
        yaw = float(np.arctan2(-R[0, 1], R[1, 1]))
    else:
        yaw = float(np.arctan2(R[1, 0], R[0, 0]))
        roll = float(np.arctan2(R[2, 1], R[2, 2]))
    return yaw, pitch, roll


def mount_from_cam(mount_roll_deg: float, mount_pitch_deg: float, mount_yaw_deg: float) -> np.ndarray:
    """``R_body_from_cam`` for a camera fixed on the body with the given mount angles (degrees)."""
    R_body_from_mount = euler_zyx_to_matrix(
        np.radians(mount_yaw_deg), np.radians(mount_pitch_deg), np.radians(mount_roll_deg)
    )
    return R_body_from_mount @ R_MOUNT_FROM_CAM


def cam_from_world_from_attitude(
    position_enu: np.ndarray,
    R_ned_from_body: np.ndarray,
    R_body_from_cam: np.ndarray,
) -> np.ndarray:
    """Compose a 4x4 OpenCV ``cam_from_world`` from a vehicle ENU position and NED attitude.

    ``position_enu``: camera centre in world ENU metres. ``R_ned_from_body``: vehicle attitude.
    ``R_body_from_cam``: the mount (see :func:`mount_from_cam`).
    """
    R_world_from_cam = R_ENU_FROM_NED @ np.asarray(R_ned_from_body) @ np.asarray(R_body_from_cam)
    return pose_matrix(R_world_from_cam.T, -R_world_from_cam.T @ np.asarray(position_enu, float))


def pose_matrix(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 homogeneous matrix from a 3x3 rotation and a translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (``world_from_cam`` from ``cam_from_world`` and back)."""
    T = np.asarray(T, dtype=np.float64)
    R = T[:3, :3]
    return pose_matrix(R.T, -R.T @ T[:3, 3])


def camera_center(cam_from_world: np.ndarray) -> np.ndarray:
    """Camera centre in world coordinates from a ``cam_from_world`` 4x4."""
    T = np.asarray(cam_from_world, dtype=np.float64)
    return -T[:3, :3].T @ T[:3, 3]


def look_at(eye_enu: np.ndarray, target_enu: np.ndarray, up_enu=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenCV ``cam_from_world`` for a camera at ``eye`` looking at ``target`` (world ENU, metres).

    Image y points away from ``up`` (down). For a straight-down view, where ``up`` is parallel to
    the viewing direction, world north is used as the image-up direction instead.
    """
    eye = np.asarray(eye_enu, dtype=np.float64)
    forward = np.asarray(target_enu, dtype=np.float64) - eye
    norm = np.linalg.norm(forward)
    if not np.isfinite(norm) or norm < 1e-12:
        raise ValueError(f"look_at: eye {eye} and target {target_enu} coincide")
    z = forward / norm
    up = np.asarray(up_enu, dtype=np.float64)
    x = np.cross(z, up)  # right = forward x up  (for OpenCV y-down)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R_world_from_cam = np.stack([x, y, z], axis=1)
    return pose_matrix(R_world_from_cam.T, -R_world_from_cam.T @ eye)


def orbit_pose(
    altitude_m: float,
    radius_m: float,
    pitch_deg: float,
    azimuth_deg: float = 0.0,
    center_enu=(0.0, 0.0, 0.0),
) -> np.ndarray:
    """``cam_from_world`` of a camera on an orbit around ``center_enu``, heading to the centre.

    The camera sits at ``radius_m`` from the centre along azimuth ``azimuth_deg`` (degrees,
    counter-clockwise from east, ENU) at ``altitude_m`` above the centre, the body yawed to face
    the centre, and the camera pitched by ``pitch_deg`` (-90 nadir, 0 horizon) with no roll.
    """
    az = np.radians(azimuth_deg)
    c = np.asarray(center_enu, dtype=np.float64)
    eye = c + np.array([radius_m * np.cos(az), radius_m * np.sin(az), altitude_m])
    # Heading toward the centre, as a NED yaw (0 = north, clockwise positive).
    to_center_enu = c[:2] - eye[:2]
    if np.linalg.norm(to_center_enu) < 1e-9:
        heading_ned = 0.0
    else:
        heading_ned = np.arctan2(to_center_enu[0], to_center_enu[1])
    R_ned_from_body = euler_zyx_to_matrix(heading_ned, 0.0, 0.0)
    return cam_from_world_from_attitude(eye, R_ned_from_body, mount_from_cam(0.0, pitch_deg, 0.0))
