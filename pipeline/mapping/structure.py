"""The structure stage in shards: SIFT per chunk of images and matching per chunk of pairs, each a
task that writes one shard file, then one step that assembles COLMAP's database from the shards.

A shard is written under a temporary name and renamed when complete, so a killed task leaves no
shard that looks finished; its name carries a digest of everything it depends on (the image
files, the cameras, the options), so a shard of other inputs is never reused. A rerun does only
the missing shards; a shard that cannot be read back (a damaged file) is named in a warning and
made again. The tasks are plain functions over paths and names: ``Tasks.run`` runs them (here
in order, in this process; ``workflows`` hands in a Dask client's). With a Dask cluster the
shard folder must be one that every worker can read and write (a shared file system).

Image ids of the assembled database follow the order of the names (1, 2, ...), not the order in
which threads finished: the same images give the same database, whichever executor made it.
"""

import hashlib
import io
import json
import logging
import os
import tempfile
import time
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

from pipeline.progress import Silent
from pipeline.textfiles import write_atomic

logger = logging.getLogger(__name__)

SIFT_CHUNK = 8  # images per SIFT task: long enough to keep a worker busy, short enough to resume from
MIN_SIFT_TASKS = 8  # fewer images per SIFT task below SIFT_CHUNK x 8 (10 images: 5 tasks of 2, not 8 + 2)
MATCH_CHUNK = 256  # image pairs per matching task (64: each task copies its images anew, 1.6x the CPU)
Pair = Tuple[str, str]


def in_process(fn: Callable, calls: Sequence[tuple], name: str, on_done: Optional[Callable] = None) -> List:
    """Run ``fn(*args)`` per argument tuple, in order, in this process (``Tasks.run``'s default)."""
    out = []
    for args in calls:
        out.append(fn(*args))
        if on_done:
            on_done(out[-1])
    return out


@dataclass
class Tasks:
    """How the structure stage's tasks run: ``run(fn, calls, name, on_done)`` returns their results
    in order (``in_process``, or a Dask client's ``workflows.executor.run_dask``); ``threads``:
    pycolmap threads per task (0: every core, for a single process; a Dask worker runs one task
    per core with 1); ``progress(total, desc, unit)`` counts images and pairs; ``seconds`` receives
    the wall time of each stage (``sift``, ``matching``, ``assembly``); ``sift_chunk`` images per
    SIFT task and ``match_chunk`` pairs per matching task (the units a killed build redoes)."""

    run: Callable = in_process
    threads: int = 0
    progress: Callable = Silent
    seconds: Dict[str, float] = field(default_factory=dict)
    sift_chunk: int = SIFT_CHUNK
    match_chunk: int = MATCH_CHUNK


def digest(value) -> str:
    """A short digest of a JSON-able value (what a shard depends on)."""
    return hashlib.sha256(json.dumps(value, sort_keys=True).encode()).hexdigest()[:12]


def _threads(threads: int) -> int:
    return threads if threads > 0 else -1  # COLMAP: -1 is every core


# ---------------------------------------------------------------------------------------------
# SIFT: an npz per chunk of images (keypoints, descriptors, cameras, the images refused and why)

@dataclass(frozen=True)
class SiftShard:
    """The SIFT of a chunk of images, an npz at ``path``."""

    path: str
    names: Tuple[str, ...]


def plan_sift(shard_dir: Path, names: Sequence[str], files: Dict[str, list],
              cameras: Optional[Dict[str, str]] = None, chunk: int = SIFT_CHUNK) -> List[SiftShard]:
    """The SIFT shards of ``names`` in chunks of ``chunk`` (fewer where that makes fewer than
    ``MIN_SIFT_TASKS``; by the number of images only, so a resumed build chunks alike); ``files``:
    name -> [name, bytes, digest] of each image (``images_fingerprint``: the same bytes in another
    folder keep their shard), ``cameras``: name -> known camera (``CameraRecord.to_json``), if any."""
    chunk = max(1, min(chunk, -(-len(names) // MIN_SIFT_TASKS)))  # a small map still spreads over the workers
    shards = []
    for k in range(0, len(names), chunk):
        part = tuple(names[k:k + chunk])
        key = digest([[files[n] for n in part], [(cameras or {}).get(n) for n in part]])
        shards.append(SiftShard(str(Path(shard_dir) / f"sift-{k // chunk:05d}-{key}.npz"), part))
    return shards


def _load(path: str, what: str, expect: Callable[[Dict[str, np.ndarray]], Optional[str]]):
    """The arrays of a finished shard (an npz: its CRCs checked as it is read); None when it is not
    made yet; ``ValueError`` naming the shard when it is damaged or ``expect`` says what is wrong."""
    if not Path(path).exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
        wrong = expect(arrays)
        if wrong:
            raise ValueError(wrong)
        return arrays
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error) as e:
        raise ValueError(f"{what} {path} is damaged ({type(e).__name__}: {e})") from None


def read_sift(shard: SiftShard) -> Optional[Dict[str, np.ndarray]]:
    """A finished SIFT shard's arrays (``_load``)."""
    def wrong(a):
        if a["chunk"].tolist() != list(shard.names):
            return "it holds another chunk of images"
        if len(a["names"]) != len(a["num_keypoints"]) or int(a["num_keypoints"].sum()) != len(a["keypoints"]) \
                or len(a["keypoints"]) != len(a["descriptors"]):
            return "its keypoints and descriptors do not add up"
        return None
    return _load(shard.path, "SIFT shard", wrong)


def _finished(read: Callable, shard) -> bool:
    """Whether ``shard`` is made (``read`` finds it whole); a damaged one is said and made again."""
    try:
        return read(shard) is not None
    except ValueError as e:
        logger.warning("%s: made again.", e)
        return False


def _save(path: str, arrays: Dict[str, np.ndarray]) -> None:
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    write_atomic(path, buffer.getvalue())


def extract_sift(shard: SiftShard, image_dir: str, cameras: Optional[Dict[str, str]], threads: int) -> dict:
    """One SIFT task: the features of ``shard.names`` (pycolmap's ``extract_features`` into a
    temporary database, one camera per image), known cameras set (their intrinsics fixed: two-view
    geometry is then calibrated), saved as the shard's npz; images that the image reader refuses are
    left out with their reason. Skipped when the shard is finished."""
    import pycolmap

    from pipeline.images import ImageReadError, read_image
    from pipeline.scene import CameraRecord
    if _finished(read_sift, shard):
        return {"names": len(shard.names), "status": "skipped"}
    t0 = time.perf_counter()
    refused, keep = {}, []
    for name in shard.names:
        try:
            read_image(Path(image_dir) / name)  # COLMAP would read a truncated JPEG in part
            keep.append(name)
        except ImageReadError as e:
            refused[name] = str(e)
    out = {k: [] for k in ("names", "num_keypoints", "keypoints", "descriptors", "model", "size", "params",
                           "prior_focal_length")}
    with tempfile.TemporaryDirectory(prefix="pixloc-sift-") as tmp:
        database = Path(tmp) / "database.db"
        if keep:
            reader = pycolmap.ImageReaderOptions()
            if cameras:
                reader.camera_model = "PINHOLE"
            options = pycolmap.FeatureExtractionOptions()
            options.num_threads = _threads(threads)
            pycolmap.extract_features(database, image_dir, image_names=keep, camera_mode=pycolmap.CameraMode.PER_IMAGE,
                                      reader_options=reader, extraction_options=options, device=pycolmap.Device.cpu)
        with pycolmap.Database.open(database) as db:
            by_name = {image.name: image for image in db.read_all_images()}
            for name in keep:
                image = by_name[name]
                camera = db.read_camera(image.camera_id)
                model, size, params, prior = (camera.model.name, (camera.width, camera.height), list(camera.params),
                                              camera.has_prior_focal_length)
                if cameras:
                    rec = CameraRecord.from_json(cameras[name])
                    model, size, params, prior = rec.model, (rec.width, rec.height), list(rec.params), True
                keypoints = np.asarray(db.read_keypoints(image.image_id), np.float32).reshape(-1, 6)
                out["names"].append(name)
                out["num_keypoints"].append(len(keypoints))
                out["keypoints"].append(keypoints)
                descriptors = db.read_descriptors(image.image_id).data
                out["descriptors"].append(np.asarray(descriptors, np.uint8).reshape(-1, 128))
                out["model"].append(model)
                out["size"].append(size)
                out["params"].append(params + [np.nan] * (MAX_PARAMS - len(params)))
                out["prior_focal_length"].append(prior)
    _save(shard.path, {
        "chunk": np.asarray(shard.names, dtype=str), "names": np.asarray(out["names"], dtype=str),
        "num_keypoints": np.asarray(out["num_keypoints"], np.int64),
        "keypoints": np.concatenate(out["keypoints"]) if keep else np.zeros((0, 6), np.float32),
        "descriptors": np.concatenate(out["descriptors"]) if keep else np.zeros((0, 128), np.uint8),
        "model": np.asarray(out["model"], dtype=str), "size": np.asarray(out["size"], np.int64).reshape(-1, 2),
        "params": np.asarray(out["params"], np.float64).reshape(-1, MAX_PARAMS),
        "prior_focal_length": np.asarray(out["prior_focal_length"], bool),
        "refused": np.asarray(list(refused), dtype=str), "reasons": np.asarray(list(refused.values()), dtype=str)})
    return {"names": len(shard.names), "status": "done", "seconds": round(time.perf_counter() - t0, 3)}


MAX_PARAMS = 16  # camera parameters per model, at most (COLMAP's FULL_OPENCV has 12)


def _copy_images(db, shards: Dict[str, str], ids: Dict[str, int], names: Sequence[str]) -> None:
    """Write the cameras, trivial rigs and frames, images, keypoints and descriptors of ``names``
    from their SIFT shards (name -> shard path) into the database ``db`` under the ids ``ids``."""
    import pycolmap
    by_shard: Dict[str, List[str]] = {}
    for name in names:
        by_shard.setdefault(shards[name], []).append(name)
    for path, wanted in by_shard.items():
        a = _load(path, "SIFT shard", lambda a: None)
        if a is None:
            raise ValueError(f"SIFT shard {path} is missing")
        ends = np.cumsum(a["num_keypoints"])
        index = {n: k for k, n in enumerate(a["names"].tolist())}
        for name in sorted(wanted, key=ids.get):
            k, new = index[name], ids[name]
            params = a["params"][k]
            camera = pycolmap.Camera.create_from_model_name(new, str(a["model"][k]), float(params[0]),
                                                            int(a["size"][k][0]), int(a["size"][k][1]))
            camera.params = params[np.isfinite(params)].tolist()
            camera.has_prior_focal_length = bool(a["prior_focal_length"][k])
            db.write_camera(camera, use_camera_id=True)
            rig = pycolmap.Rig()
            rig.rig_id = new
            rig.add_ref_sensor(camera.sensor_id)
            db.write_rig(rig, use_rig_id=True)
            frame = pycolmap.Frame()
            frame.frame_id, frame.rig_id = new, new
            frame.add_data_id(pycolmap.data_t(camera.sensor_id, new))
            db.write_frame(frame, use_frame_id=True)
            image = pycolmap.Image(name=name, camera_id=new, image_id=new)
            image.frame_id = new
            db.write_image(image, use_image_id=True)
            rows = slice(ends[k] - a["num_keypoints"][k], ends[k])
            db.write_keypoints(new, a["keypoints"][rows])
            db.write_descriptors(new, pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT,
                                                                  a["descriptors"][rows]))


# ---------------------------------------------------------------------------------------------
# matching: an npz of the matches and two-view geometries per chunk of pairs

@dataclass(frozen=True)
class MatchShard:
    path: str
    pairs: Tuple[Pair, ...]


def plan_matches(shard_dir: Path, pairs: Sequence[Pair], sift_key: Dict[str, str],
                 chunk: int = MATCH_CHUNK) -> List[MatchShard]:
    """The matching shards of ``pairs`` in chunks of ``chunk``; ``sift_key``: name -> the file name
    of the SIFT shard of that image (a new SIFT shard makes its pairs' shards new)."""
    shards = []
    for k in range(0, len(pairs), chunk):
        part = tuple(tuple(p) for p in pairs[k:k + chunk])
        key = digest([part, sorted({sift_key[n] for p in part for n in p})])
        shards.append(MatchShard(str(Path(shard_dir) / f"matches-{k // chunk:05d}-{key}.npz"), part))
    return shards


def read_matches(shard: MatchShard) -> Optional[Dict[str, np.ndarray]]:
    """A finished matching shard's arrays (``_load``)."""
    def wrong(a):
        return None if [tuple(p) for p in a["pairs"].tolist()] == list(shard.pairs) else "it lists other pairs"
    return _load(shard.path, "matching shard", wrong)


def match_pairs(shard: MatchShard, sift_shards: Dict[str, str], ids: Dict[str, int], threads: int) -> dict:
    """One matching task: SIFT matching and two-view verification of ``shard.pairs`` (pycolmap's
    ``match_image_pairs`` on a database of their images only, in a temporary folder), saved as the
    shard's npz. Skipped when the shard is finished."""
    import pycolmap
    if _finished(read_matches, shard):
        return {"pairs": len(shard.pairs), "status": "skipped"}
    t0 = time.perf_counter()
    names = sorted({n for p in shard.pairs for n in p}, key=lambda n: ids[n])
    with tempfile.TemporaryDirectory(prefix="pixloc-match-") as tmp:
        database = Path(tmp) / "database.db"
        with pycolmap.Database.open(database) as db:
            _copy_images(db, sift_shards, ids, names)
        (Path(tmp) / "pairs.txt").write_text("".join(f"{a} {b}\n" for a, b in shard.pairs))
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = str(Path(tmp) / "pairs.txt")
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = _threads(threads)
        verification = pycolmap.TwoViewGeometryOptions()
        verification.ransac.random_seed = 0  # the same pairs verify the same way on any worker
        pycolmap.match_image_pairs(database, matching_options=matching, pairing_options=pairing,
                                   verification_options=verification, device=pycolmap.Device.cpu)
        with pycolmap.Database.open(database) as db:
            arrays = _match_arrays(db, shard.pairs, ids)
    _save(shard.path, arrays)
    return {"pairs": len(shard.pairs), "status": "done", "seconds": round(time.perf_counter() - t0, 3)}


def _match_arrays(db, pairs: Sequence[Pair], ids: Dict[str, int]) -> Dict[str, np.ndarray]:
    """The matches and two-view geometries of ``pairs`` in ``db``, as arrays in the order of the
    pairs, each pair's image ids in COLMAP's order (the smaller first)."""
    import pycolmap
    out = {k: [] for k in ("matches", "num_matches", "config", "E", "F", "H", "rotation", "translation",
                           "tri_angle", "inliers", "num_inliers")}
    for a, b in pairs:
        i, j = sorted((ids[a], ids[b]))
        m = db.read_matches(i, j) if db.exists_matches(i, j) else np.zeros((0, 2), np.uint32)
        out["matches"].append(np.asarray(m, np.uint32).reshape(-1, 2))
        out["num_matches"].append(len(out["matches"][-1]))
        g = db.read_two_view_geometry(i, j) if db.exists_two_view_geometry(i, j) else pycolmap.TwoViewGeometry()
        out["config"].append(int(g.config))
        for k in ("E", "F", "H"):  # None where not estimated: NaN here
            m = getattr(g, k)
            out[k].append(np.full((3, 3), np.nan) if m is None else np.asarray(m, np.float64).reshape(3, 3))
        pose = g.cam2_from_cam1
        out["rotation"].append(np.full(4, np.nan) if pose is None else np.asarray(pose.rotation.quat, np.float64))
        out["translation"].append(np.full(3, np.nan) if pose is None else np.asarray(pose.translation, np.float64))
        out["tri_angle"].append(float(g.tri_angle))
        out["inliers"].append(np.asarray(g.inlier_matches, np.uint32).reshape(-1, 2))
        out["num_inliers"].append(len(out["inliers"][-1]))
    arrays = {k: (np.concatenate(v) if k in ("matches", "inliers") else np.asarray(v)) for k, v in out.items()}
    arrays["pairs"] = np.asarray(pairs, dtype=str).reshape(-1, 2)
    return arrays


def _write_matches(db, arrays: Dict[str, np.ndarray], ids: Dict[str, int]) -> None:
    """Write one shard's matches and two-view geometries into the assembled database."""
    import pycolmap
    ends_m = np.cumsum(arrays["num_matches"])
    ends_i = np.cumsum(arrays["num_inliers"])
    for k, (a, b) in enumerate(arrays["pairs"].tolist()):
        i, j = sorted((ids[a], ids[b]))
        matches = arrays["matches"][ends_m[k] - arrays["num_matches"][k]:ends_m[k]]
        if len(matches):
            db.write_matches(i, j, matches)
        g = pycolmap.TwoViewGeometry()
        g.config = int(arrays["config"][k])
        for m in ("E", "F", "H"):
            if np.isfinite(arrays[m][k]).all():
                setattr(g, m, arrays[m][k])
        if np.isfinite(arrays["rotation"][k]).all():
            g.cam2_from_cam1 = pycolmap.Rigid3d(pycolmap.Rotation3d(arrays["rotation"][k]), arrays["translation"][k])
        g.tri_angle = float(arrays["tri_angle"][k])
        g.inlier_matches = arrays["inliers"][ends_i[k] - arrays["num_inliers"][k]:ends_i[k]]
        db.write_two_view_geometry(i, j, g)


# ---------------------------------------------------------------------------------------------
# the stage

def build_database(database: Path, image_dir: Path, names: Sequence[str], files: Dict[str, list], pairs_conf,
                   tasks: Tasks, *, cameras: Optional[Sequence] = None,
                   cam_from_world: Optional[Sequence[np.ndarray]] = None, model: Optional[str] = None) -> List[str]:
    """SIFT of ``names`` and matching of the pairs that ``pairs_conf`` (``PairsConfig``) chooses, as
    shards in ``database``'s folder (``shards/``) made by ``tasks``, assembled into ``database``
    (made anew). ``files``: name -> [name, bytes, digest]; ``cameras`` (``CameraRecord``) and
    ``cam_from_world``: known intrinsics and poses, aligned with ``names``. Returns the names used:
    images that the image reader refuses are left out, named in a warning."""
    from pipeline.mapping.image_pairs import select_pairs, write_pairs
    from pipeline.scene import SceneError
    work_dir = Path(database).parent
    shard_dir = work_dir / "shards"
    shard_dir.mkdir(parents=True, exist_ok=True)
    known = None if cameras is None else {n: c.to_json() for n, c in zip(names, cameras)}
    sift = plan_sift(shard_dir, names, files, known, tasks.sift_chunk)
    t0 = time.perf_counter()
    _run(tasks, extract_sift, sift, lambda s: len(s.names), lambda s: read_sift(s) and {"names": len(s.names)},
         lambda s: (s, str(image_dir), known and {n: known[n] for n in s.names}, tasks.threads),
         "sift", "SIFT features", "image")
    tasks.seconds["sift"] = time.perf_counter() - t0
    refused = {}
    for shard in sift:  # the images each task's reader refused, with the reasons
        a = _load(shard.path, "SIFT shard", lambda a: None)
        refused.update(zip(a["refused"].tolist(), a["reasons"].tolist()))
    if refused:
        lines = [f"{n}: {r}" for n, r in refused.items()]
        more = f"\n  ... and {len(lines) - 20} more" if len(lines) > 20 else ""
        logger.warning("%d of %d images left out of SIFT and matching:\n  %s", len(refused), len(names),
                       "\n  ".join(lines[:20]) + more)
    keep = [k for k, n in enumerate(names) if n not in refused]
    if not keep:
        raise SceneError(f"None of the {len(names)} images in {image_dir} can be read (first: {lines[0]}).")
    used = [names[k] for k in keep]
    ids = {n: k + 1 for k, n in enumerate(used)}
    image_shard = {n: s.path for s in sift for n in s.names if n in ids}
    poses = None if cam_from_world is None else [cam_from_world[k] for k in keep]
    pairs = select_pairs(used, pairs_conf, cam_from_world=poses, image_dir=image_dir, model=model)
    write_pairs(pairs, work_dir / "pairs.txt")
    matches = plan_matches(shard_dir, pairs, {n: Path(p).name for n, p in image_shard.items()},
                           tasks.match_chunk)
    t0 = time.perf_counter()
    _run(tasks, match_pairs, matches, lambda s: len(s.pairs), lambda s: read_matches(s) and {"pairs": len(s.pairs)},
         lambda s: (s, {n: image_shard[n] for p in s.pairs for n in p}, {n: ids[n] for p in s.pairs for n in p},
                    tasks.threads), "matching", "SIFT matching", "pair")
    tasks.seconds["matching"] = time.perf_counter() - t0
    logger.info("Matched %d pairs of %d images (%s, listed in %s).", len(pairs), len(used),
                pairs_conf.resolve(len(used), cam_from_world is not None), work_dir / "pairs.txt")
    t0 = time.perf_counter()
    assemble(database, image_shard, ids, matches)
    tasks.seconds["assembly"] = time.perf_counter() - t0
    current = {Path(s.path).name for s in [*sift, *matches]}
    for stale in shard_dir.iterdir():  # shards of earlier inputs (a changed image, other pairs), killed tasks' parts
        if stale.name not in current:
            stale.unlink(missing_ok=True)
    return used


def _run(tasks: Tasks, fn: Callable, shards: Sequence, size: Callable, read: Callable, args: Callable,
         name: str, desc: str, unit: str) -> List:
    """Run ``fn`` over the shards not finished yet (``read`` None or damaged), counting ``size``
    of each as done; the results of every shard in order (the finished ones read back)."""
    results: List = [None] * len(shards)
    todo = []
    for k, shard in enumerate(shards):
        try:
            results[k] = read(shard)
        except ValueError as e:
            logger.warning("%s: made again.", e)
        if results[k] is None:
            todo.append(k)
    done = len(shards) - len(todo)
    if done:
        logger.info("%s: %d of %d shards already made (kept).", desc, done, len(shards))
    with tasks.progress(sum(size(s) for s in shards), desc, unit) as counter:
        counter.update(sum(size(shards[k]) for k in range(len(shards)) if k not in set(todo)))
        made = tasks.run(fn, [args(shards[k]) for k in todo], name,
                         lambda r: counter.update(r["names"] if "names" in r else r["pairs"]))
    for k, result in zip(todo, made):
        results[k] = result
    return results


def assemble(database: Path, image_shard: Dict[str, str], ids: Dict[str, int], matches: Sequence[MatchShard]) -> None:
    """COLMAP's database from the shards: the images in the order of their ids, then every shard's
    matches and two-view geometries; written under a temporary name, then renamed."""
    import pycolmap
    database = Path(database)
    tmp = database.with_name(f".{database.name}.{os.getpid()}.tmp")
    tmp.unlink(missing_ok=True)
    try:
        with pycolmap.Database.open(tmp) as db:
            _copy_images(db, image_shard, ids, sorted(ids, key=ids.get))
            for shard in matches:
                arrays = read_matches(shard)
                if arrays is None:
                    raise ValueError(f"matching shard {shard.path} is missing")
                _write_matches(db, arrays, ids)
        os.replace(tmp, database)
    finally:
        tmp.unlink(missing_ok=True)
