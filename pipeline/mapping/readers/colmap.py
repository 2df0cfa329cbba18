"""COLMAP models (binary or text) via pycolmap: read, reconstruct, triangulate from known poses."""

import json
import logging
import time
from dataclasses import asdict
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence

import numpy as np
import pycolmap

from pixloc.nets.registry import DEFAULT_MODEL

from pipeline.images import file_sha256, image_files
from pipeline.mapping.image_pairs import PairsConfig
from pipeline.mapping.readers.colmap_files import read_reconstruction
from pipeline.mapping.structure import Tasks, build_database
from pipeline.progress import Silent
from pipeline.scene import CameraRecord, ImageRecord, Scene, SceneError

logger = logging.getLogger(__name__)


def camera_record(camera: pycolmap.Camera) -> CameraRecord:
    return CameraRecord(camera.model.name, int(camera.width), int(camera.height),
                        tuple(float(p) for p in camera.params))


def scene_from_reconstruction(rec: pycolmap.Reconstruction, image_dir: Path,
                              tags: Optional[Dict[str, Dict[str, str]]] = None) -> Scene:
    """A Scene from a pycolmap Reconstruction; registered images only, sorted by name."""
    image_dir = Path(image_dir)
    images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    index = {im.image_id: i for i, im in enumerate(images)}
    records = [ImageRecord(im.name, image_dir / im.name, camera_record(rec.cameras[im.camera_id]),
                           np.asarray(im.cam_from_world().matrix(), dtype=np.float64),
                           dict((tags or {}).get(im.name, {})), source_id=int(im.image_id),
                           origin=f"COLMAP image_id {im.image_id}")
               for im in images]
    point_ids = sorted(rec.points3D)
    xyz = np.array([rec.points3D[p].xyz for p in point_ids], dtype=np.float64).reshape(-1, 3)
    obs_point, obs_image, obs_xy = [], [], []
    for k, pid in enumerate(point_ids):
        for el in rec.points3D[pid].track.elements:
            if el.image_id in index:
                obs_point.append(k)
                obs_image.append(index[el.image_id])
                obs_xy.append(rec.images[el.image_id].points2D[el.point2D_idx].xy)
    return Scene(records, xyz, obs_point, obs_image, np.array(obs_xy).reshape(-1, 2), point_ids)


def read_colmap(model_dir, image_dir, tags=None) -> Scene:
    """Read a COLMAP model folder (cameras/images/points3D, .bin or .txt)."""
    rec = read_reconstruction(model_dir)
    try:
        return scene_from_reconstruction(rec, image_dir, tags)
    except SceneError as e:  # an image listed twice ...: named with the model's folder
        raise SceneError(f"{model_dir}: {e}") from None


def _extract_and_match(database: Path, image_dir: Path, names: Sequence[str], pairs: PairsConfig,
                       fingerprint: dict, tasks: Tasks, cameras: Optional[Sequence[CameraRecord]] = None,
                       cam_from_world: Optional[Sequence[np.ndarray]] = None) -> List[str]:
    """SIFT features, and matches over the pairs of ``pairs``, into ``database``, as the shards of
    ``pipeline.mapping.structure`` made by ``tasks``; known intrinsics if given. Returns the names of
    the images used: those the image reader refuses are left out."""
    files = {f[0]: f for f in fingerprint["images"]}
    return build_database(database, image_dir, names, files, pairs, tasks, cameras=cameras,
                          cam_from_world=cam_from_world, model=DEFAULT_MODEL)


def _pairs_fingerprint(pairs: PairsConfig, num_images: int, posed: bool) -> dict:
    """What the pairs change in a reconstruction (nothing to record for exhaustive matching, so
    that models made before pairs were configurable are still reused)."""
    method = pairs.resolve(num_images, posed)
    if method == "exhaustive":
        return {}
    out = {"pairs": {"method": method, **{k: v for k, v in asdict(pairs).items() if k not in ("method",)}}}
    if method == "file":
        out["pairs"]["file"] = Path(pairs.path).read_text()
    return out


SFM, TRIANGULATION = "sfm", "triangulation"  # what a reconstruction's fingerprint is of (its "kind")


def images_fingerprint(image_dir: Path, names: Sequence[str], **extra) -> dict:
    """What a reconstruction depends on: its image files (name, size, digest of the bytes) and
    settings. Not the modification times: a dataset copied to another disk or machine keeps its
    reconstruction (an SfM of thousands of images takes hours)."""
    files = [[n, (image_dir / n).stat().st_size, file_sha256(image_dir / n)[:16]] if (image_dir / n).is_file()
             else [n, None, None] for n in names]
    return json.loads(json.dumps({"images": files, **extra}))


def legacy_fingerprint(image_dir: Path, fingerprint: dict) -> dict:
    """The fingerprint of the same inputs as written before content digests (size, mtime)."""
    files = []
    for n, size, _ in fingerprint["images"]:
        st = (image_dir / n).stat() if size is not None else None
        files.append([n, st.st_size if st else None, st.st_mtime_ns if st else None])
    return {**fingerprint, "images": files}


def cached_model(work_dir: Path, marker: str, model: str, fingerprint: dict,
            image_dir: Path) -> Optional[pycolmap.Reconstruction]:
    """The reconstruction a previous run finished in ``work_dir`` from the same inputs, if any.

    pycolmap's SfM and triangulation are not deterministic (threads, RANSAC): rerunning them
    would give another map, which the store then refuses. Reusing the finished model makes a
    rebuild a no-op and an interrupted build resumable. A marker of the older format (file
    times) is accepted while the files are untouched, and rewritten in the new one."""
    path = work_dir / marker
    if path.is_file() and (work_dir / model).is_dir():
        try:
            stored = json.loads(path.read_text())
            if stored in (fingerprint, legacy_fingerprint(image_dir, fingerprint)):
                logger.info("Reusing the reconstruction in %s (same inputs).", work_dir / model)
                rec = read_reconstruction(work_dir / model)
                if stored != fingerprint:
                    path.write_text(json.dumps(fingerprint))
                return rec
            logger.info("The inputs of %s changed since it was made: reconstructing again.", work_dir / model)
        except (ValueError, RuntimeError) as e:
            logger.warning("Cannot reuse %s (%s): reconstructing again.", work_dir / model, e)
    return None


def fresh_database(work_dir: Path, marker: str) -> Path:
    """An empty COLMAP database for a new reconstruction in ``work_dir``, with the marker of the
    finished one removed first (a crash after this leaves no model that looks finished)."""
    (work_dir / marker).unlink(missing_ok=True)
    database = work_dir / "database.db"
    database.unlink(missing_ok=True)
    return database


def _finish(rec: pycolmap.Reconstruction, work_dir: Path, marker: str, model: str,
            fingerprint: dict) -> pycolmap.Reconstruction:
    """Write the model and then its marker (a crash in between leaves no marker); return it as
    read back, so that a first run and a rerun build from the same bytes."""
    (work_dir / model).mkdir(parents=True, exist_ok=True)
    rec.write(str(work_dir / model))
    (work_dir / marker).write_text(json.dumps(fingerprint))
    return pycolmap.Reconstruction(str(work_dir / model))


MAPPERS = ("incremental", "global", "hierarchical")
MAX_TRACKS = 2_000_000  # global SfM keeps at most this many tracks (its memory grows with them)


def run_sfm(image_dir, work_dir, names: Optional[Sequence[str]] = None, tags=None,
            pairs: PairsConfig = PairsConfig(), progress: Callable = Silent, *, tasks: Optional[Tasks] = None,
            mapper: str = "incremental", max_tracks: int = MAX_TRACKS) -> Scene:
    """Structure-from-motion with pycolmap: SIFT and matching of ``pairs`` in shards run by
    ``tasks`` (``pipeline.mapping.structure``; in this process by default), then ``mapper``:
    ``incremental`` (COLMAP's), ``global`` (GLOMAP's rotation averaging and global positioning,
    with the focal lengths calibrated from the view graph first where no image has a prior
    focal length, and at most ``max_tracks`` tracks) or ``hierarchical`` (incremental per
    cluster of images, merged); images, pairs and the registration counted by ``progress``.

    Keeps the largest model; images it could not register are left out and logged. A model
    finished in ``work_dir`` from the same images is reused.
    """
    if mapper not in MAPPERS:
        raise ValueError(f"Unknown mapper {mapper!r}; known: {', '.join(MAPPERS)}.")
    tasks = tasks or Tasks(progress=progress)
    image_dir, work_dir = Path(image_dir), Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    names = image_files(image_dir) if names is None else list(names)
    if len(names) < 2:  # before: an IndexError while building another error's message
        raise SceneError(f"{image_dir}: {len(names)} images (JPEG or PNG files directly in the folder"
                         f"{', after --hold-out' if image_files(image_dir) else ''}) to reconstruct: SfM needs at "
                         "least 2.")
    extra = {} if mapper == "incremental" else {"mapper": mapper, "max_tracks": max_tracks}
    fingerprint = images_fingerprint(image_dir, names, kind=SFM, **_pairs_fingerprint(pairs, len(names), False),
                                     **extra)
    rec = cached_model(work_dir, "sfm.json", "model", fingerprint, image_dir)
    if rec is not None:
        return scene_from_reconstruction(rec, image_dir, tags)
    database = fresh_database(work_dir, "sfm.json")
    used = _extract_and_match(database, image_dir, names, pairs, fingerprint, tasks)
    t0 = time.perf_counter()
    models = _map(database, image_dir, work_dir / "sparse", mapper, max_tracks, len(used), tasks.progress)
    tasks.seconds["mapping"] = time.perf_counter() - t0
    if not models:
        raise SceneError(
            f"SfM could not reconstruct any model from {len(used)} images in {image_dir}"
            + (f" ({len(names) - len(used)} more could not be read)" if len(used) < len(names) else "")
            + ": no initial image pair "
            f"had enough matches with enough baseline (pairs matched: {pairs.method}). What to try: more images of "
            "the same place with overlap (each part seen by three or more), '--pairs exhaustive' to match every "
            "pair, the images at their full resolution (not downscaled copies), and images that show one scene.")
    rec = max(models.values(), key=lambda r: r.num_reg_images())
    missing = set(used) - {im.name for im in rec.images.values() if im.has_pose}
    if missing:
        logger.warning("SfM did not register %d of %d images: %s", len(missing), len(used), sorted(missing))
    rec = _finish(rec, work_dir, "sfm.json", "model", fingerprint)
    return scene_from_reconstruction(rec, image_dir, tags)


def _map(database: Path, image_dir: Path, output: Path, mapper: str, max_tracks: int, num_images: int,
         progress: Callable) -> Dict[int, pycolmap.Reconstruction]:
    """The models that ``mapper`` reconstructs from ``database`` (seeded, two threads)."""
    output.mkdir(parents=True, exist_ok=True)
    if mapper == "global":
        with pycolmap.Database.open(database) as db:
            calibrated = all(c.has_prior_focal_length for c in db.read_all_cameras())
        if not calibrated:  # GLOMAP needs calibrated two-view geometries: focal lengths from the view graph
            pycolmap.calibrate_view_graph(database)
        options = pycolmap.GlobalPipelineOptions()
        options.random_seed = 0
        options.num_threads = 2
        options.mapper.keep_max_num_tracks = max_tracks
        with progress(1, "global SfM", "model") as counter:
            models = pycolmap.global_mapping(database, image_dir, output, options=options)
            counter.update()
        return models
    if mapper == "hierarchical":
        options = pycolmap.HierarchicalPipelineOptions()
        options.num_workers = 1
        with progress(1, "hierarchical SfM", "model") as counter:
            models = pycolmap.hierarchical_mapping(database, image_dir, output, options=options)
            counter.update()
        return models
    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = 0
    options.num_threads = 2
    with progress(num_images, "SfM registration", "image") as counter:
        def registered(n: int) -> None:  # the initial pair, then one image at a time (any model)
            counter.update(max(0, min(n, counter.total - counter.done)))
        return pycolmap.incremental_mapping(database, image_dir, output, options=options,
                                            initial_image_pair_callback=lambda: registered(2),
                                            next_image_callback=lambda: registered(1))


def triangulate_known_poses(images: List[ImageRecord], image_root, work_dir, *,
                            min_track_length: int = 2, max_reprojection_error: float = 2.0,
                            pairs: PairsConfig = PairsConfig(), timings: Optional[Dict[str, float]] = None,
                            progress: Callable = Silent, tasks: Optional[Tasks] = None) -> Scene:
    """Extract and match SIFT (over ``pairs``: exhaustive for small maps, nearby cameras with
    overlapping views above that), then triangulate with the given poses and intrinsics held fixed.

    image names must be paths relative to ``image_root``. Tracks shorter than
    ``min_track_length`` or with a mean reprojection error above
    ``max_reprojection_error`` pixels are removed. ``timings``, if given, receives the seconds of
    each stage (``sift``, ``matching``, ``assembly``, ``triangulation``; nothing when a finished
    model is reused). SIFT and matching run as the shards of ``pipeline.mapping.structure``, by
    ``tasks`` (in this process by default).
    """
    image_root, work_dir = Path(image_root), Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    names = [im.name for im in images]
    by_name = {im.name: im for im in images}
    fingerprint = images_fingerprint(image_root, names, kind=TRIANGULATION, min_track_length=min_track_length,
                               max_reprojection_error=max_reprojection_error,
                               cameras=[im.camera.to_json() for im in images],
                               poses=[np.round(np.asarray(im.cam_from_world, np.float64), 12).tolist()
                                      for im in images],
                               **_pairs_fingerprint(pairs, len(images), True))
    rec = cached_model(work_dir, "triangulation.json", "model", fingerprint, image_root)
    if rec is not None:
        return _known_pose_scene(rec, image_root, by_name)
    database = fresh_database(work_dir, "triangulation.json")
    tasks = tasks or Tasks(progress=progress)
    stages = tasks.seconds if timings is None else timings
    tasks.seconds = stages
    _extract_and_match(database, image_root, names, pairs, fingerprint, tasks, [im.camera for im in images],
                       [im.cam_from_world for im in images])
    t0 = time.perf_counter()
    rec = pycolmap.Reconstruction()
    with pycolmap.Database.open(database) as db:
        for image in db.read_all_images():
            rec.add_camera_with_trivial_rig(db.read_camera(image.camera_id))
            new = pycolmap.Image(name=image.name, camera_id=image.camera_id, image_id=image.image_id)
            rec.add_image_with_trivial_frame(new, pycolmap.Rigid3d(by_name[image.name].cam_from_world))
    with tasks.progress(1, "triangulation", "model") as counter:
        options = pycolmap.IncrementalPipelineOptions()
        # COLMAP leaves out tracks seen by two images only; a map of two images has no others
        options.triangulation.ignore_two_view_tracks = len(images) > 2
        rec = pycolmap.triangulate_points(rec, database, image_root, work_dir / "triangulated", options=options)
        counter.update()
    for pid, point in list(rec.points3D.items()):
        if point.track.length() < min_track_length or point.error > max_reprojection_error:
            rec.delete_point3D(pid)
    if rec.num_points3D() == 0:
        raise SceneError("Triangulation from the known poses produced no 3D points.")
    stages["triangulation"] = time.perf_counter() - t0
    _warn_if_few_triangulated(rec, database)
    logger.info("Triangulated %d points from %d images with known poses in %.0f s (SIFT %.0f s, matching %.0f s).",
                rec.num_points3D(), len(names), stages["triangulation"], stages.get("sift", 0.0),
                stages.get("matching", 0.0))
    rec = _finish(rec, work_dir, "triangulation.json", "model", fingerprint)
    return _known_pose_scene(rec, image_root, by_name)


MIN_TRIANGULATED_SHARE = 0.1  # of the verified keypoints; a right map of the shared scenes triangulates far more


def _warn_if_few_triangulated(rec: pycolmap.Reconstruction, database: Path) -> float:
    """Warn where the known poses triangulate few of the keypoints that two-view geometry verified
    between the images (the images agree with each other, their poses do not): how a pose
    convention error shows (OpenCV axes read as OpenGL's, camera-to-world read as world-to-camera),
    which otherwise builds a small map without a word. Returns that share."""
    with pycolmap.Database.open(database) as db:
        verified = set()
        for pair_id, geometry in zip(*db.read_two_view_geometries()):
            first, second = pycolmap.pair_id_to_image_pair(pair_id)
            for a, b in geometry.inlier_matches:
                verified.add((first, int(a)))
                verified.add((second, int(b)))
    triangulated = sum(1 for image in rec.images.values() for p in image.points2D if p.has_point3D())
    share = triangulated / max(len(verified), 1)
    if verified and share < MIN_TRIANGULATED_SHARE:
        logger.warning("The known poses triangulated %d of the %d keypoints that SIFT matched and verified between "
                       "the images (%.0f %%; %d points for %d images): the poses do not agree with the images. Check "
                       "the source's pose convention (camera-to-world or world-to-camera, OpenCV or OpenGL axes).",
                       triangulated, len(verified), 100 * share, rec.num_points3D(), rec.num_reg_images())
    return share


def _known_pose_scene(rec: pycolmap.Reconstruction, image_root: Path, by_name: Dict[str, ImageRecord]) -> Scene:
    scene = scene_from_reconstruction(rec, image_root)
    # Keep the caller's records (tags, depth), in the scene's order.
    scene.images = [by_name[im.name] for im in scene.images]
    return scene
