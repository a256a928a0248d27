"""Camera poses at frame time from MAVLink telemetry.

- Which component is the autopilot: the first HEARTBEAT whose ``autopilot`` is not
  MAV_AUTOPILOT_INVALID and whose type is a vehicle (not a GCS, companion, gimbal or camera).
  Position and attitude come only from it; gimbal attitude from any component of its system.
- Time: every boot-timed message is mapped to companion unix µs by :mod:`telemetry.timesync`.
- Position: GLOBAL_POSITION_INT (lat, lon 1e-7 deg, AMSL alt mm) → local ENU metres (WGS84,
  float64), origin = the first valid fix (lat = lon = 0 means no fix).
- Attitude: ATTITUDE_QUATERNION if present, else ATTITUDE; both are ``R_ned_from_body`` (FRD).
- Camera: the fixed mount of camera.json, or gimbal telemetry when present (GIMBAL_DEVICE_ATTITUDE_STATUS:
  earth-frame yaw when the yaw-lock / in-earth-frame flag is set, else yaw relative to the vehicle
  heading with earth-levelled roll and pitch; MOUNT_STATUS likewise, timed by receive time).
- Interpolation at each frame's capture time: linear position, sign-safe slerp for attitude, never
  across a gap longer than ``max_gap_s``; such frames (and frames outside the telemetry span) are
  unposed with a reason.
"""

from __future__ import annotations

import bisect
import logging
from dataclasses import dataclass, field

import numpy as np

from telemetry.camera import Camera
from telemetry.frames import (
    R_MOUNT_FROM_CAM,
    cam_from_world_from_attitude,
    euler_zyx_to_matrix,
    matrix_to_euler_zyx,
    mount_from_cam,
    rot_z,
)
from telemetry.geodesy import geodetic_to_enu
from telemetry.mavlink import is_autopilot_heartbeat
from telemetry.posesfile import Origin, PoseEntry, PosesFile
from telemetry.quat import euler_zyx_to_quat, matrix_to_quat, quat_to_matrix, slerp
from telemetry.timesync import ClockMap, TimeSyncConfig, build_clock_maps

log = logging.getLogger(__name__)

_GIMBAL_EARTH_FLAGS = 4 | 2048  # GIMBAL_DEVICE_FLAGS_YAW_LOCK | GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME


class TelemetryError(ValueError):
    """Telemetry that cannot give any pose (no autopilot, no position...)."""


@dataclass
class PosesConfig:
    """Options of :func:`poses_from_telemetry`."""

    #: never interpolate across a telemetry gap longer than this (seconds).
    max_gap_s: float = 0.5
    #: use gimbal telemetry when present (overrides the fixed mount).
    use_gimbal: bool = True
    timesync: TimeSyncConfig = field(default_factory=TimeSyncConfig)


@dataclass
class Track:
    """Time-stamped samples (unix µs, sorted, unique) of a vector quantity."""

    t_us: np.ndarray
    values: np.ndarray
    name: str
    #: extra per-sample data (e.g. gimbal flags)
    flags: np.ndarray | None = None

    @classmethod
    def build(cls, name: str, samples: list[tuple[int, np.ndarray, int]]) -> Track:
        samples = sorted(samples, key=lambda s: s[0])
        t, v, f = [], [], []
        for ti, vi, fi in samples:
            if t and ti == t[-1]:
                continue  # duplicate (same message twice, or two messages at one time)
            t.append(ti)
            v.append(vi)
            f.append(fi)
        values = np.array(v, dtype=np.float64).reshape(len(t), -1) if t else np.zeros((0, 3))
        return cls(np.array(t, dtype=np.int64), values, name, np.array(f, dtype=np.int64))

    def __len__(self) -> int:
        return len(self.t_us)

    def bracket(self, t_us: int, max_gap_us: int) -> tuple[int, int, float] | str:
        """(i, j, u) with t between samples i and j (u in [0, 1]) or the reason it cannot be."""
        if len(self.t_us) == 0:
            return f"no {self.name} telemetry"
        if t_us < self.t_us[0]:
            return f"before the first {self.name} sample ({(self.t_us[0] - t_us) / 1e6:.3f} s early)"
        if t_us > self.t_us[-1]:
            return f"after the last {self.name} sample ({(t_us - self.t_us[-1]) / 1e6:.3f} s late)"
        j = bisect.bisect_left(self.t_us, t_us)
        if self.t_us[j] == t_us:
            return j, j, 0.0
        i = j - 1
        gap = int(self.t_us[j] - self.t_us[i])
        if gap > max_gap_us:
            return f"{self.name} telemetry gap of {gap / 1e6:.3f} s (limit {max_gap_us / 1e6:.3f} s)"
        return i, j, float(t_us - self.t_us[i]) / gap

    def gaps(self, min_gap_us: int) -> list[tuple[int, int]]:
        """(start, end) unix µs of the gaps longer than ``min_gap_us``."""
        d = np.diff(self.t_us)
        return [(int(self.t_us[k]), int(self.t_us[k + 1])) for k in np.nonzero(d > min_gap_us)[0]]


@dataclass
class TelemetryTracks:
    """Everything extracted from a tlog that poses need."""

    autopilot: tuple[int, int]
    origin: Origin | None
    position: Track  # ENU metres of origin
    attitude: Track  # quaternion (w, x, y, z), R_ned_from_body
    gimbal: Track  # quaternion (w, x, y, z); flags say the frame
    clock_maps: dict[tuple[int, int], ClockMap]
    warnings: list[str]
    attitude_message: str

    @property
    def time_source(self) -> str:
        cm = self.clock_maps.get(self.autopilot)
        return cm.source if cm else "none"


def find_autopilot(records) -> tuple[int, int] | None:
    """(system, component) of the first vehicle autopilot HEARTBEAT, else the main position sender."""
    for rec in records:
        m = rec.msg
        if is_autopilot_heartbeat(m):
            return m.get_srcSystem(), m.get_srcComponent()
    counts: dict[tuple[int, int], int] = {}
    for rec in records:
        if rec.msg.get_type() == "GLOBAL_POSITION_INT":
            key = (rec.msg.get_srcSystem(), rec.msg.get_srcComponent())
            counts[key] = counts.get(key, 0) + 1
    if counts:
        return max(counts, key=counts.get)
    return None


def dedupe(records) -> list:
    """Drop byte-identical repeats of a frame (same sequence number, time and payload): a message
    that arrived twice, e.g. over two routes. Different messages never share all their bytes."""
    seen: set[bytes] = set()
    out = []
    for rec in records:
        # only time-bearing messages: two equal status messages 256 sequence numbers apart are not repeats
        if rec.raw in seen and getattr(rec.msg, "time_boot_ms", None) is not None:
            continue
        seen.add(rec.raw)
        out.append(rec)
    return out


def extract_tracks(records, config: PosesConfig | None = None) -> TelemetryTracks:
    """Position, attitude and gimbal tracks (companion unix µs) of the autopilot in ``records``."""
    cfg = config or PosesConfig()
    warnings: list[str] = []
    records = dedupe(records)
    ap = find_autopilot(records)
    if ap is None:
        raise TelemetryError("no autopilot in the telemetry (no vehicle HEARTBEAT and no GLOBAL_POSITION_INT)")
    if not any(r.msg.get_type() == "HEARTBEAT" and (r.msg.get_srcSystem(), r.msg.get_srcComponent()) == ap
               for r in records):
        warnings.append(f"no autopilot HEARTBEAT; using {ap}, the main GLOBAL_POSITION_INT sender")
    cmaps = build_clock_maps(records, cfg.timesync)
    for cm in cmaps.values():
        warnings.extend(cm.warnings)
    ap_map = cmaps.get(ap)
    pos_raw: list[tuple[int, float, float, float]] = []
    att: list[tuple[int, float, float, float]] = []
    attq: list[tuple[int, np.ndarray, int]] = []
    gim: list[tuple[int, np.ndarray, int]] = []
    for i, rec in enumerate(records):
        m = rec.msg
        typ = m.get_type()
        src = (m.get_srcSystem(), m.get_srcComponent())
        if src == ap and typ in ("GLOBAL_POSITION_INT", "ATTITUDE", "ATTITUDE_QUATERNION"):
            t = ap_map.unix_us(i) if ap_map else None
            if t is None:
                continue
            if typ == "GLOBAL_POSITION_INT":
                if m.lat == 0 and m.lon == 0:
                    continue  # no fix
                pos_raw.append((t, m.lat * 1e-7, m.lon * 1e-7, m.alt * 1e-3))
            elif typ == "ATTITUDE":
                att.append((t, m.yaw, m.pitch, m.roll))
            else:
                q = np.array([m.q1, m.q2, m.q3, m.q4], dtype=np.float64)
                if np.isfinite(q).all() and np.linalg.norm(q) > 0.5:
                    attq.append((t, q / np.linalg.norm(q), 0))
        elif cfg.use_gimbal and src[0] == ap[0] and typ == "GIMBAL_DEVICE_ATTITUDE_STATUS":
            cm = cmaps.get(src)
            t = cm.unix_us(i) if cm else None
            q = np.array(m.q, dtype=np.float64)
            if t is not None and np.isfinite(q).all() and np.linalg.norm(q) > 0.5:
                gim.append((t, q / np.linalg.norm(q), int(m.flags)))
        elif cfg.use_gimbal and src == ap and typ == "MOUNT_STATUS":
            # centi-degrees: a = pitch, b = roll, c = yaw relative to the vehicle; no time field.
            R = euler_zyx_to_matrix(np.radians(m.pointing_c / 100.0), np.radians(m.pointing_a / 100.0),
                                    np.radians(m.pointing_b / 100.0))
            gim.append((rec.t_unix_us, matrix_to_quat(R), 0))
    origin = None
    pos_samples: list[tuple[int, np.ndarray, int]] = []
    if pos_raw:
        pos_raw.sort(key=lambda s: s[0])
        _, lat0, lon0, alt0 = pos_raw[0]
        origin = Origin(lat0, lon0, alt0)
        arr = np.array(pos_raw, dtype=np.float64)
        enu = geodetic_to_enu(arr[:, 1], arr[:, 2], arr[:, 3], (lat0, lon0, alt0))
        pos_samples = [(int(p[0]), e, 0) for p, e in zip(pos_raw, enu, strict=True)]
    att_samples: list[tuple[int, np.ndarray, int]] = []
    if att and not attq:
        a = np.array(att, dtype=np.float64)
        good = np.isfinite(a[:, 1:]).all(axis=1)
        q = euler_zyx_to_quat(a[good, 1], a[good, 2], a[good, 3])
        att_samples = [(t, qi, 0) for t, qi in zip((x[0] for x, g in zip(att, good, strict=True) if g), q, strict=True)]
    att_name = "ATTITUDE_QUATERNION" if attq else "ATTITUDE"
    return TelemetryTracks(
        autopilot=ap, origin=origin,
        position=Track.build("position", pos_samples),
        attitude=Track.build("attitude", attq or att_samples),
        gimbal=Track.build("gimbal", gim),
        clock_maps=cmaps, warnings=warnings, attitude_message=att_name)


def _interp_quat(track: Track, br) -> np.ndarray:
    i, j, u = br
    return slerp(track.values[i], track.values[j], u)


def pose_at(tracks: TelemetryTracks, t_us: int, R_body_from_cam: np.ndarray, config: PosesConfig) -> np.ndarray | str:
    """OpenCV ``cam_from_world`` (world = ENU of the origin) at companion time ``t_us``, or a reason."""
    gap = int(config.max_gap_s * 1e6)
    bp = tracks.position.bracket(t_us, gap)
    if isinstance(bp, str):
        return bp
    ba = tracks.attitude.bracket(t_us, gap)
    if isinstance(ba, str):
        return ba
    i, j, u = bp
    pos = (1.0 - u) * tracks.position.values[i] + u * tracks.position.values[j]
    R_ned_from_body = quat_to_matrix(_interp_quat(tracks.attitude, ba))
    if len(tracks.gimbal):
        bg = tracks.gimbal.bracket(t_us, gap)
        if isinstance(bg, str):
            return bg
        R_g = quat_to_matrix(_interp_quat(tracks.gimbal, bg))
        flags = int(tracks.gimbal.flags[bg[0]])
        if flags & _GIMBAL_EARTH_FLAGS:
            R_ned_from_gimbal = R_g
        else:
            # Follow mode: yaw relative to the vehicle heading, roll and pitch earth-levelled.
            # Rz(yaw_v + yaw_g) Ry(pitch_g) Rx(roll_g) = Rz(yaw_v) @ R_g: no Euler split (nadir-safe).
            yaw_vehicle = matrix_to_euler_zyx(R_ned_from_body)[0]
            R_ned_from_gimbal = rot_z(yaw_vehicle) @ R_g
        return cam_from_world_from_attitude(pos, R_ned_from_gimbal, R_MOUNT_FROM_CAM)
    return cam_from_world_from_attitude(pos, R_ned_from_body, R_body_from_cam)


def poses_from_telemetry(records, frames: list[tuple[str, int]], camera: Camera,
                         config: PosesConfig | None = None) -> tuple[PosesFile, TelemetryTracks]:
    """The poses file (source "telemetry") for ``frames`` = [(name, t_unix_us)] from tlog ``records``."""
    cfg = config or PosesConfig()
    tracks = extract_tracks(records, cfg)
    if tracks.origin is None:
        raise TelemetryError("no valid GLOBAL_POSITION_INT fix from the autopilot: cannot place any frame")
    R_body_from_cam = mount_from_cam(camera.mount.roll_deg, camera.mount.pitch_deg, camera.mount.yaw_deg)
    entries = []
    for name, t in frames:
        res = pose_at(tracks, int(t), R_body_from_cam, cfg)
        if isinstance(res, str):
            entries.append(PoseEntry(name, int(t), None, "telemetry", res))
        else:
            entries.append(PoseEntry(name, int(t), res, "telemetry"))
    n_bad = sum(not e.posed for e in entries)
    if n_bad:
        log.warning("%d of %d frames unposed (first reason: %s)", n_bad, len(entries),
                    next(e.reason for e in entries if not e.posed))
    return PosesFile(tracks.origin, camera, entries), tracks
