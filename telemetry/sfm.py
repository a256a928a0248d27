"""Structure from motion seeded by telemetry or GPS priors (pycolmap): the library API.

Entry point: :func:`refine_poses`. Inputs are images, a camera, and one :class:`Prior` per frame
(capture time, a prior camera position in local ENU metres with its 1-sigma noise, and optionally
a full prior ``cam_from_world`` from telemetry attitude). The pipeline:

1. SIFT features on CPU (image size capped by :attr:`SfmOptions.max_image_size`);
2. matching of image pairs that are close in capture time (sequential) or in prior position
   (spatial), each pair geometrically verified (:func:`candidate_pairs`);
3. initial poses: the telemetry poses where the priors carry attitude; for position-only priors
   (geotagged photos) pycolmap's incremental mapper builds partial models that are each aligned
   to the prior positions by a robust similarity and merged;
4. points are triangulated from these poses (kept fixed); frames still without a pose are
   registered by PnP against those points, else by the relative pose to their best verified
   partner with the centre on that pair's baseline at the prior distance;
5. bundle adjustment refines poses and points with the prior positions as a Gaussian prior
   (covariance = prior noise) and a Cauchy-robust reprojection loss, outlier points filtered and
   tracks re-triangulated between rounds; prior attitudes then enter the model's rigid gauge as
   one bias-like measurement (:meth:`_Context._attitude_gauge`);
6. every frame is checked (observations, prior deviation); a frame that fails keeps its prior
   pose with ``source = "telemetry"`` and an explicit ``reason``; a run that degenerates as a
   whole (too few matches, too few registered frames, a pycolmap error) does the same for every
   frame.

All geometry is in the flight's local ENU metric frame; internally coordinates are centred on
the median prior position (float64 throughout). Poses are OpenCV ``cam_from_world`` 4x4.
"""

from __future__ import annotations

import logging
import math
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from telemetry.camera import Camera
from telemetry.frames import camera_center, pose_matrix

log = logging.getLogger(__name__)


class SfmInputError(ValueError):
    """Inputs that cannot describe a flight (missing images, mismatched priors, ...)."""


@dataclass
class Prior:
    """What telemetry (or EXIF) says about one frame before SfM.

    ``position_enu``: camera centre, local ENU metres. ``sigma_m``: its 1-sigma noise, either one
    number (all axes) or (east, north, up). ``cam_from_world``: optional full 4x4 OpenCV pose from
    telemetry attitude + position (None for position-only priors, e.g. geotagged photos).
    ``t_unix_us``: capture time (unix µs) or None. Non-finite values are treated as absent.
    """

    frame: str
    t_unix_us: int | None
    position_enu: np.ndarray | None
    sigma_m: float | tuple[float, float, float] = 1.0
    cam_from_world: np.ndarray | None = None
    attitude_sigma_deg: float = 2.0
    """1-sigma of the prior attitude (per axis), used to weigh it against the positions."""

    def sigma_vec(self) -> np.ndarray:
        s = np.broadcast_to(np.asarray(self.sigma_m, dtype=np.float64), (3,)).copy()
        if not np.all(np.isfinite(s)) or np.any(s <= 0):
            raise SfmInputError(f"{self.frame}: prior sigma must be finite and positive, got {self.sigma_m}")
        return s

    def finite_position(self) -> np.ndarray | None:
        if self.position_enu is None:
            return None
        p = np.asarray(self.position_enu, dtype=np.float64).reshape(-1)
        return p if p.shape == (3,) and np.all(np.isfinite(p)) else None

    def finite_pose(self) -> np.ndarray | None:
        if self.cam_from_world is None:
            return None
        T = np.asarray(self.cam_from_world, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            return None
        R = T[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0:
            return None
        return T


@dataclass
class SfmOptions:
    """Knobs of :func:`refine_poses`; the defaults suit 0.3-1.2 Mpx drone frames."""

    max_image_size: int = 1200
    """Longest image side for feature extraction, px (keypoints are rescaled to full size)."""
    max_num_features: int = 4096
    """SIFT features kept per image."""
    sift_first_octave: int = 0
    """SIFT's first octave: 0 works on the (capped) image, -1 upsamples it 2x first (≈4x slower, more
    small-scale features)."""
    sequential_overlap: int = 6
    """Match each frame with this many following frames in capture-time order."""
    spatial_neighbors: int = 12
    """Also match each frame with up to this many nearest frames by prior position."""
    spatial_max_distance_m: float = 80.0
    """Spatial matching radius around each prior position, metres."""
    min_pair_inliers: int = 15
    """Verified matches a pair needs to count."""
    refine_intrinsics: bool = False
    """Refine focal length and radial distortion (use when intrinsics come from EXIF)."""
    min_frame_observations: int = 20
    """A frame needs this many triangulated points to count as registered."""
    min_registered_fraction: float = 0.5
    """Below this fraction of registered frames the whole run is treated as failed."""
    max_prior_deviation_sigma: float = 6.0
    """A refined centre further than this many prior sigmas from the prior is rejected."""
    max_reprojection_px: float = 4.0
    """Points with a larger mean reprojection error are removed after each BA round."""
    ba_rounds: int = 2
    """Bundle-adjustment / filtering / re-triangulation rounds."""
    ba_max_iterations: int = 50
    """Ceres iterations per bundle-adjustment round."""
    num_threads: int = -1
    """Worker threads (-1: all cores)."""
    seed: int = 0
    """Seed for every RANSAC and the mapper. Same inputs + seed + ``num_threads=1`` give the same result bit for
    bit; with more threads the order of parallel work can move poses by centimetres (seen once in CI: 4 cm)."""


@dataclass
class FramePose:
    """Outcome for one frame: ``cam_from_world`` (OpenCV 4x4, ENU) or None, its source and why."""

    frame: str
    t_unix_us: int | None
    cam_from_world: np.ndarray | None
    source: str  # "sfm" | "telemetry"
    reason: str | None = None
    stats: dict = field(default_factory=dict)


@dataclass
class SfmResult:
    """Everything :func:`refine_poses` found. Points are ENU metres (float64) with RGB uint8."""

    frames: list[FramePose]
    camera: Camera
    points_xyz: np.ndarray
    points_rgb: np.ndarray
    points_error_px: np.ndarray
    points_track_length: np.ndarray
    report: dict
    reconstruction: object | None = None
    """The final ``pycolmap.Reconstruction`` in ENU (None when SfM failed as a whole)."""

    @property
    def num_refined(self) -> int:
        return sum(f.source == "sfm" for f in self.frames)


# ---------------------------------------------------------------------------------------------
# camera conversion


def camera_to_colmap(camera: Camera, refine_intrinsics: bool):
    """Our :class:`Camera` as a pycolmap camera (RADIAL when refining, else OPENCV)."""
    import pycolmap

    if refine_intrinsics:
        f = 0.5 * (camera.fx + camera.fy)
        k1, k2 = camera.distortion[0], camera.distortion[1]
        params = [f, camera.cx, camera.cy, k1, k2]
        model = "RADIAL"
    else:
        params = [camera.fx, camera.fy, camera.cx, camera.cy, *camera.distortion]
        model = "OPENCV"
    cam = pycolmap.Camera.create_from_model_name(1, model, params[0], camera.width, camera.height)
    cam.params = np.asarray(params, dtype=np.float64)
    cam.has_prior_focal_length = True
    return cam


def camera_from_colmap(cam, template: Camera) -> Camera:
    """Back from pycolmap (RADIAL / OPENCV / PINHOLE / SIMPLE_*) keeping the template's mount."""
    p = [float(v) for v in cam.params]
    name = cam.model_name
    if name == "OPENCV":
        fx, fy, cx, cy, k1, k2, p1, p2 = p
    elif name == "RADIAL":
        fx = fy = p[0]
        cx, cy, k1, k2 = p[1:5]
        p1 = p2 = 0.0
    elif name == "SIMPLE_RADIAL":
        fx = fy = p[0]
        cx, cy, k1 = p[1:4]
        k2 = p1 = p2 = 0.0
    elif name == "PINHOLE":
        fx, fy, cx, cy = p
        k1 = k2 = p1 = p2 = 0.0
    else:
        raise ValueError(f"unsupported COLMAP camera model {name}")
    return Camera(int(cam.width), int(cam.height), fx, fy, cx, cy, (k1, k2, p1, p2), template.mount)


# ---------------------------------------------------------------------------------------------
# small geometry helpers


def _rigid_from_matrix(T: np.ndarray):
    import pycolmap

    return pycolmap.Rigid3d(np.asarray(T, dtype=np.float64)[:3, :4])


def _matrix_from_rigid(rigid) -> np.ndarray:
    M = np.eye(4)
    M[:3, :4] = rigid.matrix()
    return M


def _shift_pose(T: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """``cam_from_world`` in a world shifted by ``-offset`` (x_new = x_old - offset)."""
    S = T.copy()
    S[:3, 3] = T[:3, 3] + T[:3, :3] @ offset
    return S


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _exp_so3(w: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(w))
    K = _skew(w)
    if th < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + math.sin(th) / th * K + (1 - math.cos(th)) / th**2 * K @ K


def _log_so3(R: np.ndarray) -> np.ndarray:
    c = float(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))
    th = math.acos(c)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if th < 1e-9:
        return 0.5 * v
    return th / (2.0 * math.sin(th)) * v


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle of ``Ra @ Rb.T`` in degrees (0 for equal rotations)."""
    c = (np.trace(Ra @ Rb.T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def colinearity(points: np.ndarray) -> float:
    """Ratio of the second to the first singular value of centred points (0: on a line)."""
    P = np.asarray(points, dtype=np.float64)
    if len(P) < 3:
        return 0.0
    s = np.linalg.svd(P - P.mean(axis=0), compute_uv=False)
    return float(s[1] / s[0]) if s[0] > 1e-9 else 0.0


# ---------------------------------------------------------------------------------------------
# the pipeline


def candidate_pairs(priors: list[Prior], options: SfmOptions) -> list[tuple[int, int]]:
    """Image pairs worth matching (indices into ``priors``), sorted and unique.

    Sequential: each frame with the next ``sequential_overlap`` frames in capture-time order (frames
    without a time keep their list position). Spatial: each frame with up to ``spatial_neighbors``
    nearest frames whose prior positions lie within ``spatial_max_distance_m`` (3D).
    """
    n = len(priors)
    keys = [(p.t_unix_us if p.t_unix_us is not None else -1, k) for k, p in enumerate(priors)]
    if all(p.t_unix_us is not None for p in priors):
        order = [k for _, k in sorted(keys)]
    else:
        order = list(range(n))
    pairs = set()
    for a in range(n):
        for b in range(a + 1, min(n, a + 1 + max(1, options.sequential_overlap))):
            i, j = order[a], order[b]
            pairs.add((min(i, j), max(i, j)))
    pos = [p.finite_position() for p in priors]
    idx = [k for k, p in enumerate(pos) if p is not None]
    if len(idx) >= 2 and options.spatial_neighbors > 0:
        P = np.array([pos[k] for k in idx])
        D = np.linalg.norm(P[:, None, :] - P[None, :, :], axis=-1)
        for a, i in enumerate(idx):
            near = [b for b in np.argsort(D[a], kind="stable") if b != a and D[a, b] <= options.spatial_max_distance_m]
            for b in near[: options.spatial_neighbors]:
                j = idx[b]
                pairs.add((min(i, j), max(i, j)))
    return sorted(pairs)


def _validate(images: list[Path], priors: list[Prior], camera: Camera) -> tuple[Path, list[str]]:
    if not images:
        raise SfmInputError("no images given")
    if len(priors) != len(images):
        raise SfmInputError(f"{len(images)} images but {len(priors)} priors")
    images = [Path(p) for p in images]
    root = images[0].parent
    names = []
    for path, prior in zip(images, priors, strict=True):
        if not path.is_file():
            raise SfmInputError(f"{path}: no such image")
        if path.parent != root:
            raise SfmInputError(f"all images must be in one folder; {path} is not in {root}")
        if prior.frame != path.name:
            raise SfmInputError(f"prior for {prior.frame!r} does not match image {path.name!r} (same order)")
        prior.sigma_vec()
        names.append(path.name)
    if len(set(names)) != len(names):
        raise SfmInputError("image names must be unique")
    return root, names


def refine_poses(images: list[Path], camera: Camera, priors: list[Prior], workdir: Path,
                 options: SfmOptions | None = None) -> SfmResult:
    """Refine the poses of ``images`` (one folder) seeded by ``priors`` (same order), in ENU.

    ``workdir`` receives the COLMAP database and intermediate models (it is cleared first).
    Raises :class:`SfmInputError` for inputs that do not describe a flight; any failure of the
    reconstruction itself ends in a result whose frames keep their priors with a reason.
    """
    import pycolmap

    options = options or SfmOptions()
    image_dir, names = _validate(images, priors, camera)
    workdir = Path(workdir)
    if workdir.exists():
        shutil.rmtree(workdir)
    workdir.mkdir(parents=True)
    pycolmap.set_random_seed(options.seed)

    positions = [p.finite_position() for p in priors]
    known = np.array([p for p in positions if p is not None])
    if len(known) == 0:
        return _failed(priors, camera, "no finite prior position: the model cannot be georeferenced",
                       {"stage": "input"})
    offset = np.median(known, axis=0)
    log.info("SfM on %d frames (centred on ENU %s)", len(names), np.round(offset, 2))

    ctx = _Context(pycolmap, options, camera, priors, names, image_dir, workdir, offset)
    old_level = pycolmap.logging.minloglevel
    if not log.isEnabledFor(logging.DEBUG):
        pycolmap.logging.minloglevel = 2  # COLMAP's own INFO/WARNING chatter only at -vv
    try:
        return ctx.run()
    except _Degenerate as exc:
        log.warning("SfM degenerate: %s", exc)
        return _failed(priors, camera, str(exc), {"stage": exc.stage, **exc.details})
    except RuntimeError as exc:  # a COLMAP-side failure: keep the priors, say why, keep the traceback
        log.exception("SfM failed inside pycolmap")
        return _failed(priors, camera, f"pycolmap error: {exc}", {"stage": "pycolmap"})
    finally:
        pycolmap.logging.minloglevel = old_level


class _Degenerate(Exception):
    def __init__(self, message: str, stage: str, **details):
        super().__init__(message)
        self.stage = stage
        self.details = details


def _fallback_frame(prior: Prior, reason: str, stats: dict | None = None) -> FramePose:
    pose = prior.finite_pose()
    stats = dict(stats or {})
    pos = prior.finite_position()
    if pos is not None:
        stats.setdefault("prior_position_enu", [float(v) for v in pos])
    if pose is None:
        reason = f"{reason}; no prior attitude, so no pose (prior position kept in prior_position_enu)"
    return FramePose(prior.frame, prior.t_unix_us, pose, "telemetry", reason, stats)


def _failed(priors: list[Prior], camera: Camera, reason: str, report: dict) -> SfmResult:
    frames = [_fallback_frame(p, f"SfM failed: {reason}") for p in priors]
    report = {"ok": False, "reason": reason, "num_frames": len(priors), "num_registered": 0,
              "registered_fraction": 0.0, **report}
    empty = np.zeros((0, 3))
    return SfmResult(frames, camera, empty, np.zeros((0, 3), np.uint8), np.zeros(0), np.zeros(0, int), report)


class _Context:
    """One run of the pipeline (holds the pycolmap objects; not part of the API)."""

    def __init__(self, pycolmap, options, camera, priors, names, image_dir, workdir, offset):
        self.pc = pycolmap
        self.o = options
        self.camera = camera
        self.priors = priors
        self.names = names
        self.image_dir = image_dir
        self.workdir = workdir
        self.offset = offset
        self.db_path = workdir / "database.db"
        self.report: dict = {"ok": True, "num_frames": len(names)}

    # -- stages -----------------------------------------------------------------------------
    def run(self) -> SfmResult:
        import time

        t0 = time.perf_counter()
        self._database_and_features()
        t1 = time.perf_counter()
        self._match()
        t2 = time.perf_counter()
        rec = self._initial_model()
        rec = self._triangulate(rec)
        rec = self._register_missing(rec)
        rec = self._register_relative(rec)
        rec = self._bundle_adjust(rec)
        self._attitude_gauge(rec)
        t3 = time.perf_counter()
        self.report["seconds"] = {"features": t1 - t0, "matching": t2 - t1, "mapping": t3 - t2,
                                  "total": t3 - t0}
        return self._result(rec)

    def _database_and_features(self) -> None:
        pc, o = self.pc, self.o
        db = pc.Database.open(str(self.db_path))
        cam = camera_to_colmap(self.camera, o.refine_intrinsics)
        cam_id = db.write_camera(cam)
        db.close()
        reader = pc.ImageReaderOptions()
        reader.existing_camera_id = cam_id
        reader.camera_model = cam.model_name
        pc.import_images(str(self.db_path), str(self.image_dir), pc.CameraMode.SINGLE,
                         image_names=self.names, options=reader)
        ext = pc.FeatureExtractionOptions()
        ext.max_image_size = o.max_image_size
        ext.num_threads = o.num_threads
        ext.use_gpu = False
        ext.sift.max_num_features = o.max_num_features
        ext.sift.first_octave = o.sift_first_octave
        pc.extract_features(str(self.db_path), str(self.image_dir), image_names=self.names,
                            camera_mode=pc.CameraMode.SINGLE, reader_options=reader,
                            extraction_options=ext, device=pc.Device.cpu)
        db = pc.Database.open(str(self.db_path))
        self.images = {img.name: img for img in db.read_all_images()}
        missing = [n for n in self.names if n not in self.images]
        if missing:
            db.close()
            raise _Degenerate(f"COLMAP could not read {len(missing)} images (e.g. {missing[0]})", "features")
        self.image_ids = {n: self.images[n].image_id for n in self.names}
        self.name_of = {v: k for k, v in self.image_ids.items()}
        self.keypoints = {iid: np.asarray(db.read_keypoints(iid), dtype=np.float64)[:, :2]
                          for iid in self.name_of}
        n_kp = [len(k) for k in self.keypoints.values()]
        self.report["keypoints_per_image"] = {"median": float(np.median(n_kp)), "min": int(min(n_kp))}
        # position priors (centred ENU, covariance from the prior noise); COLMAP's own EXIF GPS
        # priors (WGS84, written by import_images) are replaced by ours
        db.clear_pose_priors()
        self.pose_priors = {}
        for name, prior in zip(self.names, self.priors, strict=True):
            pos = prior.finite_position()
            if pos is None:
                continue
            pp = pc.PosePrior()
            pp.corr_data_id = self.images[name].data_id
            pp.position = pos - self.offset
            pp.position_covariance = np.diag(prior.sigma_vec() ** 2)
            pp.coordinate_system = pc.PosePriorCoordinateSystem.CARTESIAN
            pp.pose_prior_id = db.write_pose_prior(pp)
            self.pose_priors[name] = pp
        db.close()

    def _verification(self):
        v = self.pc.TwoViewGeometryOptions()
        v.min_num_inliers = self.o.min_pair_inliers
        v.ransac.random_seed = self.o.seed
        return v

    def _matching_options(self):
        m = self.pc.FeatureMatchingOptions()
        m.num_threads = self.o.num_threads
        m.use_gpu = False
        return m

    def _match(self) -> None:
        pc, o = self.pc, self.o
        pairs = candidate_pairs(self.priors, self.o)
        self.report["candidate_pairs"] = len(pairs)
        pair_file = self.workdir / "pairs.txt"
        pair_file.write_text("".join(f"{self.names[i]} {self.names[j]}\n" for i, j in pairs))
        imported = pc.ImportedPairingOptions()
        imported.match_list_path = pair_file
        pc.match_image_pairs(str(self.db_path), self._matching_options(), imported, self._verification(),
                             device=pc.Device.cpu)
        db = pc.Database.open(str(self.db_path))
        pair_ids, geoms = db.read_two_view_geometries()
        db.close()
        self.pairs = {}
        for pid, g in zip(pair_ids, geoms, strict=True):
            inl = np.asarray(g.inlier_matches)
            if len(inl) >= o.min_pair_inliers:
                a, b = pc.pair_id_to_image_pair(pid)
                self.pairs[(int(a), int(b))] = inl
        self.report["verified_pairs"] = len(self.pairs)
        matched = {i for pair in self.pairs for i in pair}
        self.report["frames_with_verified_match"] = len(matched)
        if not self.pairs:
            raise _Degenerate("too few matches: no image pair has "
                              f"{o.min_pair_inliers} geometrically verified matches (low texture?)",
                              "matching", verified_pairs=0,
                              keypoints_per_image=self.report["keypoints_per_image"])
        if len(matched) < o.min_registered_fraction * len(self.names):
            raise _Degenerate(f"too few matches: only {len(matched)} of {len(self.names)} frames have a "
                              "verified partner", "matching", verified_pairs=len(self.pairs))

    def _empty_reconstruction(self):
        """A reconstruction holding the database's camera and images (with keypoints), no poses."""
        pc = self.pc
        db = pc.Database.open(str(self.db_path))
        rec = pc.Reconstruction()
        for cam in db.read_all_cameras():
            rec.add_camera_with_trivial_rig(cam)
        db.close()
        for name in self.names:
            iid = self.image_ids[name]
            img = pc.Image(name=name, keypoints=self.keypoints[iid], camera_id=self.images[name].camera_id,
                           image_id=iid)
            rec.add_image_with_trivial_frame(img)
        return rec

    def _initial_model(self):
        """Reconstruction in centred ENU with every frame that has an initial pose registered."""
        rec = self._empty_reconstruction()
        self.initial_source = {}
        for name, prior in zip(self.names, self.priors, strict=True):
            T = prior.finite_pose()
            if T is not None:
                self._set_pose(rec, name, _shift_pose(T, self.offset))
                self.initial_source[name] = "prior attitude"
        missing = [n for n in self.names if n not in self.initial_source]
        if missing and len(self.pose_priors) >= 3:
            self._poses_from_mapper(rec, missing)
        self.report["initial_poses"] = {k: sum(v == k for v in self.initial_source.values())
                                        for k in set(self.initial_source.values())}
        return rec

    def _set_pose(self, rec, name: str, T_centred: np.ndarray) -> None:
        iid = self.image_ids[name]
        if not rec.exists_image(iid):  # triangulate_points keeps only registered images
            img = self.pc.Image(name=name, keypoints=self.keypoints[iid], camera_id=self.images[name].camera_id,
                                image_id=iid)
            rec.add_image_with_trivial_frame(img, _rigid_from_matrix(T_centred))
            return
        frame = rec.frame(iid)
        frame.rig_from_world = _rigid_from_matrix(T_centred)
        if not rec.frame(iid).has_pose or iid not in set(rec.reg_frame_ids()):
            rec.register_frame(iid)

    def _poses_from_mapper(self, rec, missing: list[str]) -> None:
        """Incremental mapping with position priors; each partial model aligned to the priors."""
        pc, o = self.pc, self.o
        opts = pc.IncrementalPipelineOptions()
        opts.use_prior_position = True
        opts.use_robust_loss_on_prior_position = True
        opts.random_seed = o.seed
        opts.mapper.random_seed = o.seed
        opts.triangulation.random_seed = o.seed
        opts.num_threads = o.num_threads
        opts.min_model_size = 3
        opts.ba_refine_focal_length = o.refine_intrinsics
        opts.ba_refine_extra_params = o.refine_intrinsics
        opts.ba_refine_principal_point = False
        opts.extract_colors = False
        out = self.workdir / "mapper"
        out.mkdir(exist_ok=True)
        models = pc.incremental_mapping(str(self.db_path), str(self.image_dir), str(out), opts)
        models = sorted(models.values(), key=lambda r: -r.num_reg_images())
        self.report["mapper_models"] = [int(m.num_reg_images()) for m in models]
        sigma = np.median([p.sigma_vec().max() for p in self.priors])
        todo = set(missing)
        for k, model in enumerate(models):
            names = [model.image(i).name for i in model.reg_image_ids()]
            if not todo.intersection(names):
                continue
            src = np.array([model.image(i).projection_center() for i in model.reg_image_ids()])
            tgt_list = [self.pose_priors[n].position if n in self.pose_priors else None for n in names]
            keep = [j for j, t in enumerate(tgt_list) if t is not None]
            if len(keep) < 3:
                continue
            tgt = np.array([tgt_list[j] for j in keep])
            if colinearity(tgt) < 0.05:
                log.info("mapper model %d (%d images): prior positions colinear, orientation about the "
                         "line unobservable; its frames are left to PnP", k, len(names))
                continue
            ransac = pc.RANSACOptions()
            ransac.max_error = 3.0 * sigma
            ransac.random_seed = o.seed
            est = pc.estimate_sim3d_robust(src[keep], tgt, ransac)
            if est is None or est["num_inliers"] < 3:
                continue
            sim = est["tgt_from_src"]
            model.transform(sim)
            for i in model.reg_image_ids():
                name = model.image(i).name
                if name in todo:
                    self._set_pose(rec, name, _matrix_from_rigid(model.image(i).cam_from_world()))
                    self.initial_source[name] = f"mapper model {k} aligned to priors"
                    todo.discard(name)

    def _triangulate(self, rec, clear_points: bool = True):
        """Triangulate (``clear_points``: from scratch, else continue and merge tracks) from the current
        poses, which stay fixed; two-view tracks are kept (frames seen by one partner need them)."""
        pc = self.pc
        if rec.num_reg_images() < 2:
            raise _Degenerate(f"only {rec.num_reg_images()} frame(s) have an initial pose; nothing to "
                              "triangulate from", "initial poses")
        opts = pc.IncrementalPipelineOptions()
        opts.random_seed = self.o.seed
        opts.triangulation.random_seed = self.o.seed
        opts.triangulation.ignore_two_view_tracks = False
        opts.num_threads = self.o.num_threads
        out = self.workdir / "triangulated"
        out.mkdir(exist_ok=True)
        rec = pc.triangulate_points(rec, str(self.db_path), str(self.image_dir), str(out),
                                    clear_points=clear_points, options=opts, refine_intrinsics=False)
        return rec

    def _register_missing(self, rec, min_inliers: int = 30):
        """PnP for frames without a pose, from their verified matches to triangulated points."""
        pc = self.pc
        for _ in range(3):
            reg = set(rec.reg_image_ids())
            added = 0
            for name in self.names:
                iid = self.image_ids[name]
                if iid in reg:
                    continue
                p2d, p3d, seen = [], [], set()
                for (a, b), inl in self.pairs.items():
                    if iid not in (a, b):
                        continue
                    other = b if a == iid else a
                    if other not in reg:
                        continue
                    cols = (0, 1) if a == iid else (1, 0)
                    other_img = rec.image(other)
                    for m in inl:
                        p = other_img.points2D[int(m[cols[1]])]
                        if p.has_point3D() and p.point3D_id not in seen:
                            seen.add(p.point3D_id)
                            p2d.append(self.keypoints[iid][int(m[cols[0]])])
                            p3d.append(rec.point3D(p.point3D_id).xyz)
                if len(p2d) < min_inliers:
                    continue
                est_opts = pc.AbsolutePoseEstimationOptions()
                est_opts.ransac.max_error = 8.0
                est_opts.ransac.random_seed = self.o.seed
                ans = pc.estimate_and_refine_absolute_pose(np.array(p2d), np.array(p3d),
                                                           rec.camera(self.images[name].camera_id), est_opts)
                if ans is None or ans["num_inliers"] < min_inliers:
                    continue
                self._set_pose(rec, name, _matrix_from_rigid(ans["cam_from_world"]))
                self.initial_source[name] = "PnP against triangulated points"
                added += 1
            if not added:
                break
            rec = self._triangulate(rec)
        self.report["initial_poses"] = {k: sum(v == k for v in self.initial_source.values())
                                        for k in set(self.initial_source.values())}
        return rec

    def _register_relative(self, rec):
        """Frames PnP could not place (their matches see no triangulated point) but that share a
        verified pair with a registered frame: rotation from the pair's relative pose, centre from
        the prior position. Bundle adjustment (with two-view tracks) then refines them; the per-frame
        checks reject any that do not converge."""
        pc = self.pc
        reg = set(rec.reg_image_ids())
        added = 0
        for name, prior in zip(self.names, self.priors, strict=True):
            iid = self.image_ids[name]
            pos = prior.finite_position()
            if iid in reg or pos is None:
                continue
            partners = [((a, b), inl) for (a, b), inl in self.pairs.items()
                        if iid in (a, b) and (b if a == iid else a) in reg]
            if not partners:
                continue
            (a, b), inl = max(partners, key=lambda x: len(x[1]))
            other = b if a == iid else a
            cols = (0, 1) if a == iid else (1, 0)
            pts_new = self.keypoints[iid][inl[:, cols[0]].astype(int)]
            pts_reg = self.keypoints[other][inl[:, cols[1]].astype(int)]
            cam = rec.camera(self.images[name].camera_id)
            ransac = pc.RANSACOptions()
            ransac.max_error = 4.0
            ransac.random_seed = self.o.seed
            ans = pc.estimate_relative_pose(cam, pts_reg, cam, pts_new, ransac)
            if ans is None or ans["num_inliers"] < self.o.min_pair_inliers:
                continue
            T_rel = _matrix_from_rigid(ans["cam2_from_cam1"])
            T_reg = _matrix_from_rigid(rec.image(other).cam_from_world())
            R = T_rel[:3, :3] @ T_reg[:3, :3]
            # centre along the pair's baseline direction (epipolar-consistent), at the prior distance
            c_reg = camera_center(T_reg)
            direction = T_reg[:3, :3].T @ (-T_rel[:3, :3].T @ T_rel[:3, 3])
            norm = np.linalg.norm(direction)
            c = pos - self.offset
            if norm > 1e-9:
                c = c_reg + direction / norm * np.linalg.norm(c - c_reg)
            self._set_pose(rec, name, pose_matrix(R, -R @ c))
            self.initial_source[name] = f"relative pose to {self.name_of[other]} + prior position"
            added += 1
        if added:
            rec = self._triangulate(rec)
        return rec

    def _bundle_adjust(self, rec):
        pc, o = self.pc, self.o
        for round_ in range(max(1, o.ba_rounds)):
            ba = pc.BundleAdjustmentOptions()
            ba.refine_focal_length = o.refine_intrinsics
            ba.refine_extra_params = o.refine_intrinsics
            ba.refine_principal_point = False
            ba.print_summary = False
            ba.ceres.loss_function_type = pc.LossFunctionType.CAUCHY
            ba.ceres.loss_function_scale = 1.0
            ba.ceres.solver_options.num_threads = o.num_threads
            ba.ceres.solver_options.max_num_iterations = self.o.ba_max_iterations
            prior_opts = pc.PosePriorBundleAdjustmentOptions()
            prior_opts.alignment_ransac.random_seed = o.seed
            config = pc.BundleAdjustmentConfig()
            reg = set(rec.reg_image_ids())
            for iid in reg:
                config.add_image(iid)
            if not o.refine_intrinsics:
                for cid in rec.cameras:
                    config.set_constant_cam_intrinsics(cid)
            priors = [self.pose_priors[self.name_of[i]] for i in sorted(reg)
                      if self.name_of[i] in self.pose_priors]
            adjuster = pc.create_pose_prior_bundle_adjuster(ba, prior_opts, config, priors, rec)
            summary = adjuster.solve()
            removed = self._filter_points(rec)
            log.info("BA round %d: %s, removed %d outlier points, %d points left", round_,
                     getattr(summary, "termination_type", "?"), removed, rec.num_points3D())
            if round_ < o.ba_rounds - 1:
                rec = self._triangulate(rec, clear_points=False)
        return rec

    def _attitude_gauge(self, rec) -> None:
        """Fuse the prior attitudes into the model's gauge.

        Position priors fix the model's similarity only as well as the prior positions' spread allows
        (a short arc or a straight line leaves the rotation about it loose). A final rigid correction
        (small rotation about the camera centroid + translation) minimises the prior position
        residuals over their sigma plus the mean prior attitude residual over the attitude sigma
        (treated as one bias-like measurement), then moves the whole model.
        """
        pc = self.pc
        rows, rhs = [], []
        reg = sorted(rec.reg_image_ids())
        centres = {i: np.asarray(rec.image(i).projection_center()) for i in reg}
        m = np.mean(list(centres.values()), axis=0)
        att_e, att_sigma = [], []
        for i in reg:
            name = self.name_of[i]
            prior = self.priors[self.names.index(name)]
            pos = prior.finite_position()
            if pos is not None:
                c = centres[i]
                w = 1.0 / prior.sigma_vec()
                d = c - m
                J = np.hstack([-_skew(d), np.eye(3)])  # d c' / d(omega, t)
                rows.append(J * w[:, None])
                rhs.append((pos - self.offset - c) * w)
            Tp = prior.finite_pose()
            if Tp is not None:
                Rk = _matrix_from_rigid(rec.image(i).cam_from_world())[:3, :3]
                att_e.append(_log_so3(Tp[:3, :3].T @ Rk))  # world-frame attitude discrepancy
                att_sigma.append(math.radians(max(prior.attitude_sigma_deg, 1e-3)))
        n_att = len(att_e)
        if n_att < 3:
            return
        # AHRS errors drift slowly: over one flight they are mostly a common bias, so all frames
        # together tell the model's rotation only to about one attitude sigma (one residual, not N).
        w = 1.0 / float(np.median(att_sigma))
        rows.append(np.hstack([np.eye(3), np.zeros((3, 3))]) * w)
        rhs.append(np.mean(att_e, axis=0) * w)
        A, b = np.vstack(rows), np.concatenate(rhs)
        x, *_ = np.linalg.lstsq(A, b, rcond=None)
        omega, t = x[:3], x[3:]
        R = _exp_so3(omega)
        # x' = R (x - m) + m + t
        sim = pc.Sim3d(1.0, pc.Rotation3d(R), m + t - R @ m)
        rec.transform(sim)
        self.report["attitude_gauge"] = {"rotation_deg": float(np.degrees(np.linalg.norm(omega))),
                                         "translation_m": float(np.linalg.norm(t)), "frames": n_att}

    def _filter_points(self, rec) -> int:
        rec.update_point_3d_errors()
        bad = [pid for pid, p in rec.points3D.items()
               if not np.isfinite(p.error) or p.error > self.o.max_reprojection_px or p.track.length() < 2
               or not np.all(np.isfinite(p.xyz))]
        for pid in bad:
            rec.delete_point3D(pid)
        return len(bad)

    # -- result -----------------------------------------------------------------------------
    def _per_image_errors(self, rec) -> dict[int, tuple[int, float]]:
        out = {}
        for iid in rec.reg_image_ids():
            img = rec.image(iid)
            cam = rec.camera(img.camera_id)
            T = _matrix_from_rigid(img.cam_from_world())
            xy, xyz = [], []
            for p in img.points2D:
                if p.has_point3D():
                    xy.append(p.xy)
                    xyz.append(rec.point3D(p.point3D_id).xyz)
            if not xy:
                out[iid] = (0, float("nan"))
                continue
            pc_ = np.array(xyz) @ T[:3, :3].T + T[:3, 3]
            proj = cam.img_from_cam(pc_)
            err = np.linalg.norm(np.asarray(proj) - np.array(xy), axis=1)
            out[iid] = (len(xy), float(np.mean(err)))
        return out

    def _result(self, rec) -> SfmResult:
        o = self.o
        errs = self._per_image_errors(rec)
        reg = set(rec.reg_image_ids())
        frames: list[FramePose] = []
        for name, prior in zip(self.names, self.priors, strict=True):
            iid = self.image_ids[name]
            if iid not in reg:
                frames.append(_fallback_frame(prior, "not registered: too few verified matches to "
                                              "triangulated points"))
                continue
            n_obs, err = errs[iid]
            T = _shift_pose(_matrix_from_rigid(rec.image(iid).cam_from_world()), -self.offset)
            stats = {"observations": n_obs, "reprojection_px": err,
                     "initial_pose": self.initial_source.get(name)}
            pos = prior.finite_position()
            dev_sigma = 0.0
            if pos is not None:
                d = camera_center(T) - pos
                stats["position_change_m"] = float(np.linalg.norm(d))
                dev_sigma = float(np.linalg.norm(d / prior.sigma_vec()))
                stats["position_change_sigma"] = dev_sigma
            Tp = prior.finite_pose()
            if Tp is not None:
                stats["rotation_change_deg"] = rotation_angle_deg(T[:3, :3], Tp[:3, :3])
            if n_obs < o.min_frame_observations:
                frames.append(_fallback_frame(prior, f"too few triangulated points ({n_obs} < "
                                              f"{o.min_frame_observations})", stats))
            elif not np.all(np.isfinite(T)) or not math.isfinite(err):
                frames.append(_fallback_frame(prior, "refined pose not finite", stats))
            elif dev_sigma > o.max_prior_deviation_sigma:
                frames.append(_fallback_frame(prior, f"refined centre {stats['position_change_m']:.2f} m "
                                              f"({dev_sigma:.1f} sigma) from the prior", stats))
            else:
                frames.append(FramePose(name, prior.t_unix_us, T, "sfm", None, stats))
        for f in frames:  # the COLMAP model holds exactly the frames whose SfM pose is kept
            iid = self.image_ids[f.frame]
            if f.source != "sfm" and iid in reg:
                rec.deregister_frame(rec.image(iid).frame_id)
        n_ok = sum(f.source == "sfm" for f in frames)
        frac = n_ok / len(frames)
        self.report["initial_poses"] = {k: sum(v == k for v in self.initial_source.values())
                                        for k in sorted(set(self.initial_source.values()))}
        if frac < o.min_registered_fraction:
            raise _Degenerate(f"low registration: {n_ok} of {len(frames)} frames refined "
                              f"(< {o.min_registered_fraction:.0%})", "registration",
                              num_registered=n_ok)
        # back to uncentred ENU
        shift = self.pc.Sim3d(1.0, self.pc.Rotation3d(), self.offset)
        rec.transform(shift)
        try:
            rec.extract_colors_for_all_images(str(self.image_dir))
        except Exception as exc:  # noqa: BLE001 - colours are cosmetic; report and go on
            log.warning("could not extract point colours: %s", exc)
        pids = sorted(rec.points3D)
        xyz = np.array([rec.point3D(p).xyz for p in pids]).reshape(-1, 3)
        rgb = np.array([rec.point3D(p).color for p in pids], dtype=np.uint8).reshape(-1, 3)
        perr = np.array([rec.point3D(p).error for p in pids], dtype=np.float64)
        tl = np.array([rec.point3D(p).track.length() for p in pids], dtype=np.int64)
        refined_cam = camera_from_colmap(rec.camera(next(iter(rec.cameras))), self.camera)
        changes = [f.stats["position_change_m"] for f in frames if f.source == "sfm"
                   and "position_change_m" in f.stats]
        rot_changes = [f.stats["rotation_change_deg"] for f in frames if f.source == "sfm"
                       and "rotation_change_deg" in f.stats]
        ok_err = [f.stats["reprojection_px"] for f in frames if f.source == "sfm"]
        self.report.update({
            "num_registered": n_ok, "registered_fraction": frac,
            "mean_reprojection_px": float(rec.compute_mean_reprojection_error()),
            "mean_frame_reprojection_px": float(np.mean(ok_err)) if ok_err else None,
            "num_points": int(len(pids)), "mean_track_length": float(tl.mean()) if len(tl) else 0.0,
            "median_position_change_m": float(np.median(changes)) if changes else None,
            "median_rotation_change_deg": float(np.median(rot_changes)) if rot_changes else None,
            "unregistered": {f.frame: f.reason for f in frames if f.source != "sfm"},
            "camera": refined_cam.to_json(), "enu_offset_m": [float(v) for v in self.offset],
        })
        return SfmResult(frames, refined_cam, xyz, rgb, perr, tl, self.report, rec)


def umeyama(src: np.ndarray, tgt: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``tgt ≈ s R src + t`` (Umeyama 1991) for (N,3) point sets, N ≥ 3."""
    src = np.asarray(src, dtype=np.float64)
    tgt = np.asarray(tgt, dtype=np.float64)
    if src.shape != tgt.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"need two (N>=3, 3) point sets of equal shape, got {src.shape} and {tgt.shape}")
    mu_s, mu_t = src.mean(axis=0), tgt.mean(axis=0)
    xs, xt = src - mu_s, tgt - mu_t
    cov = xt.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    var_s = (xs**2).sum() / len(src)
    s = float(np.trace(np.diag(D) @ S) / var_s) if with_scale and var_s > 0 else 1.0
    t = mu_t - s * R @ mu_s
    return s, R, t


def pose_errors(estimated: list[np.ndarray], truth: list[np.ndarray], align: bool) -> dict:
    """Rotation (deg) and centre (m) errors of ``cam_from_world`` poses against truth.

    With ``align`` one similarity (fitted to the centres) maps the estimates onto the truth first;
    its scale is reported. Returns medians, means and per-frame arrays.
    """
    C_est = np.array([camera_center(T) for T in estimated])
    C_true = np.array([camera_center(T) for T in truth])
    s, R, t = 1.0, np.eye(3), np.zeros(3)
    if align:
        s, R, t = umeyama(C_est, C_true)
    rot, pos = [], []
    for T, Tt, c, ct in zip(estimated, truth, C_est, C_true, strict=True):
        R_cw = T[:3, :3] @ R.T  # cam_from_world after the world moved by R
        rot.append(rotation_angle_deg(R_cw, Tt[:3, :3]))
        pos.append(float(np.linalg.norm(s * R @ c + t - ct)))
    rot, pos = np.array(rot), np.array(pos)
    return {"scale": s, "median_rot_deg": float(np.median(rot)), "median_pos_m": float(np.median(pos)),
            "mean_rot_deg": float(rot.mean()), "mean_pos_m": float(pos.mean()), "rot_deg": rot, "pos_m": pos}
