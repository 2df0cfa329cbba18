"""Benchmark: the structure stage of map building (SIFT, matching, triangulation or SfM).

Part ``workers``: the photo city's references nearest its centre (``--city-images`` of them, 480 x
360, fine stains for SIFT; the scale benchmark's S4 city), triangulated from their known poses with
the structure stage's shards (``pipeline.mapping.structure``) on a local Dask cluster of 1 and of 2
worker processes (one pycolmap thread each; the cluster started and its workers' imports done
before the clock starts), each from an empty work folder: seconds per stage, the speed-up of 2
workers over 1 per stage, the peak memory of each worker process and of this one, and whether
both builds made the same database (every keypoint, descriptor, match and inlier) and the same
number of points.

Part ``sfm``: structure from motion of the posed real scenes' images (their poses unused) and of the
city's, with each ``--mappers`` entry (``pipeline.mapping.readers.colmap.MAPPERS``), in this
process (SIFT and matching once per scene, their shards shared by the mappers; the mapper timed
alone): seconds, images registered, and the poses' accuracy after a similarity alignment to the
known ones (``align_error``): median position error in % of the scene's scale (the median distance of
the known camera centres to their centroid) and median rotation error.
"""

import argparse
import json
import resource
import shutil
import time
from pathlib import Path
from typing import Dict, List, Sequence

import numpy as np

from pipeline.runtime import shared_folder

SCENES = ("templeRing", "dino", "kermit", "beer", "herzjesus", "fountain")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--shared", type=Path, default=shared_folder(),
                   help="the shared data folder (default: $PIXLOC_SHARED, else ../shared)")
    p.add_argument("--work", type=Path, default=Path("outputs/benchmark-mapping"), help="work folder")
    p.add_argument("--parts", nargs="+", default=["workers", "sfm"], choices=["workers", "sfm"],
                   help="workers: SIFT and matching on 1 and 2 Dask workers; sfm: the mappers against known poses")
    p.add_argument("--city-images", type=int, nargs="+", default=[250],
                   help="workers: the city's references per run (nearest its centre)")
    p.add_argument("--sfm-city-images", type=int, nargs="*", default=[250],
                   help="sfm: the city's references per run (none: the real scenes only)")
    p.add_argument("--scenes", nargs="*", default=list(SCENES), choices=SCENES,
                   help="sfm: the accuracy benchmark's posed real scenes")
    p.add_argument("--mappers", nargs="+", default=["incremental", "global"],
                   choices=["incremental", "global", "hierarchical"], help="sfm: the mappers compared")
    p.add_argument("--seed", type=int, default=0, help="the city's seed")
    p.set_defaults(func=main)


def city(args) -> List:
    """The S4 city's references, nearest its centre first."""
    from pipeline.data.city import CityConfig, generate_city
    from pipeline.data.synthetic import read_synthetic
    from pipeline.regions import camera_centres
    from pipeline.scene import CameraRecord
    root = args.work / "city-10x10"
    generate_city(root, CityConfig(seed=args.seed, blocks=(10, 10), detail=0.3), queries_per_condition=0,
                  camera=CameraRecord("PINHOLE", 480, 360, (375.0, 375.0, 240.0, 180.0)))
    mapping, _ = read_synthetic(root)
    centres = camera_centres(np.stack([im.cam_from_world for im in mapping]))
    middle = centres[:, :2].min(0) / 2 + centres[:, :2].max(0) / 2
    order = np.argsort(np.linalg.norm(centres[:, :2] - middle, axis=1), kind="stable")
    return [mapping[i] for i in order], root


def _peak_rss() -> int:
    """This process's peak resident memory since ``_reset_peak``, bytes (``VmHWM``; a forked worker's
    ``ru_maxrss`` would start at its parent's)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _reset_peak() -> None:
    """Start the peak resident memory again from the current one (Linux: ``clear_refs`` 5)."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def _warm() -> bool:
    import pycolmap  # noqa: F401 - a worker's imports, before the clock starts

    import pipeline.images  # noqa: F401
    import pipeline.mapping.structure  # noqa: F401
    _reset_peak()
    return True


def workers_rows(args) -> List[Dict]:
    from pipeline.mapping.image_pairs import PairsConfig
    from pipeline.mapping.readers.colmap import triangulate_known_poses
    from pipeline.mapping.structure import Tasks
    from workflows.executor import Session
    ordered, root = city(args)
    rows = []
    for n in args.city_images:
        images = sorted(ordered[:n], key=lambda im: im.name)
        for workers in (1, 2):
            work = args.work / f"workers-{n}-{workers}"
            shutil.rmtree(work, ignore_errors=True)
            with Session(sync=False, workers=workers) as session:
                session.client.run(_warm)
                _reset_peak()
                tasks = Tasks(run=session.run, threads=1)
                t0 = time.perf_counter()
                scene = triangulate_known_poses(images, root, work, pairs=PairsConfig("spatial"), tasks=tasks)
                elapsed = time.perf_counter() - t0
                peaks = session.client.run(_peak_rss)
            rows.append({"images": n, "workers": workers, "seconds": elapsed, **tasks.seconds,
                         "points": len(scene.points), "worker_peak_mib": max(peaks.values()) / 2**20,
                         "client_peak_mib": _peak_rss() / 2**20, "database": str(work / "database.db")})
            print(f"  {n} images, {workers} worker(s): {elapsed:.0f} s, {len(scene.points)} points", flush=True)
    return rows


def same_database(a: str, b: str) -> bool:
    """Every image (id, name, camera), keypoint, descriptor, match and inlier equal."""
    import pycolmap
    digests = []
    for path in (a, b):
        import hashlib
        h = hashlib.sha256()
        with pycolmap.Database.open(path) as db:
            for im in sorted(db.read_all_images(), key=lambda im: im.image_id):
                cam = db.read_camera(im.camera_id)
                h.update(f"{im.image_id} {im.name} {cam.model.name} {list(cam.params)}".encode())
                h.update(db.read_keypoints(im.image_id).tobytes())
                h.update(np.asarray(db.read_descriptors(im.image_id).data).tobytes())
            ids, geometries = db.read_two_view_geometries()
            for pair_id, g in sorted(zip(ids, geometries), key=lambda x: x[0]):
                i, j = pycolmap.pair_id_to_image_pair(pair_id)
                h.update(np.asarray(db.read_matches(i, j)).tobytes() + np.asarray(g.inlier_matches).tobytes())
        digests.append(h.hexdigest())
    return digests[0] == digests[1]


def align_error(known: Dict[str, np.ndarray], found: Dict[str, np.ndarray]) -> Dict[str, float]:
    """Median position error (% of the scale: the median distance of the known centres to their
    centroid) and rotation error (degrees) of ``found`` (name -> cam_from_world 4x4) after the
    similarity that best maps it onto the known poses: its rotation from the cameras' orientations
    (the rotation nearest the mean of each camera's ``found_from_known``; the camera centres alone
    leave it free about their line or plane, as in a forward-facing capture), then its scale and
    translation from the centres (least squares)."""
    names = sorted(set(known) & set(found))
    if len(names) < 3:
        return {"position_pct": float("nan"), "rotation_deg": float("nan")}

    def centre(T):
        return -T[:3, :3].T @ T[:3, 3]
    # cam_from_known = cam_from_found @ found_from_known: found_from_known = R_found^T R_known per camera
    U, _, Vt = np.linalg.svd(sum(found[n][:3, :3].T @ known[n][:3, :3] for n in names))
    R = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt  # found_from_known
    X = np.stack([R.T @ centre(found[n]) for n in names])  # found centres, rotated into the known axes
    Y = np.stack([centre(known[n]) for n in names])
    mx, my = X.mean(0), Y.mean(0)
    s = ((X - mx) * (Y - my)).sum() / max(((X - mx) ** 2).sum(), 1e-300)
    scale = np.median(np.linalg.norm(Y - my, axis=1))
    pos = np.linalg.norm(s * (X - mx) + my - Y, axis=1) / scale * 100
    rot = []
    for n in names:
        dR = found[n][:3, :3] @ R @ known[n][:3, :3].T
        rot.append(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
    return {"position_pct": float(np.median(pos)), "rotation_deg": float(np.median(rot))}


def posed_scene(args, key: str):
    """A real scene's posed images (the accuracy benchmark's source) and their folder."""
    import dataclasses

    from .accuracy import SPLITS
    source = SPLITS[key].source
    source = dataclasses.replace(source, path=args.shared / source.path,
                                 images=args.shared / source.images if source.images else None)
    return source.format.images(source)


def sfm_rows(args) -> List[Dict]:
    from pipeline.mapping.readers.colmap import run_sfm
    from pipeline.mapping.structure import Tasks
    jobs = [(key, posed_scene(args, key)) for key in args.scenes]
    if args.sfm_city_images:
        ordered, _ = city(args)
        jobs += [(f"city {n}", sorted(ordered[:n], key=lambda im: im.name)) for n in args.sfm_city_images]
    rows = []
    for key, images in jobs:
        root = Path(_common_parent([im.path for im in images]))
        names = [str(Path(im.path).relative_to(root)) for im in images]
        known = {n: np.asarray(im.cam_from_world) for n, im in zip(names, images)}
        work = args.work / f"sfm-{key.replace(' ', '-')}"
        shards = work / "shards"
        for mapper in args.mappers:
            folder = work / mapper
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir(parents=True)
            if shards.exists():
                (folder / "shards").symlink_to(shards.resolve())  # SIFT and matching made once per scene
            tasks = Tasks()
            _reset_peak()
            t0 = time.perf_counter()
            try:
                scene = run_sfm(root, folder, names, tasks=tasks, mapper=mapper)
                found = {im.name: np.asarray(im.cam_from_world) for im in scene.images}
                error = align_error(known, found)
                registered, points = len(scene.images), len(scene.points)
            except Exception as e:  # noqa: BLE001 - a mapper that fails is a row with its reason
                registered, points, error = 0, 0, {"position_pct": float("nan"), "rotation_deg": float("nan")}
                print(f"  {key} {mapper}: failed: {type(e).__name__}: {str(e)[:200]}", flush=True)
            if not shards.exists() and (folder / "shards").is_dir():
                shutil.move(str(folder / "shards"), shards)
                (folder / "shards").symlink_to(shards.resolve())
            rows.append({"scene": key, "mapper": mapper, "images": len(names), "registered": registered,
                         "points": points, "seconds": time.perf_counter() - t0, **tasks.seconds, **error,
                         "peak_mib": _peak_rss() / 2**20})
            print(f"  {key} {mapper}: {registered}/{len(names)} registered, {tasks.seconds.get('mapping', 0):.1f} s "
                  f"mapping, {error['position_pct']:.2f} %, {error['rotation_deg']:.2f} deg", flush=True)
    return rows


def _common_parent(paths: Sequence) -> str:
    import os
    return os.path.commonpath([str(Path(p).parent) for p in paths])


def main(args: argparse.Namespace) -> int:
    args.work.mkdir(parents=True, exist_ok=True)
    if "workers" in args.parts:
        rows = workers_rows(args)
        (args.work / "workers-rows.json").write_text(json.dumps(rows, indent=1))
        print("\n| structure stage, city, known poses | images | workers | SIFT s | matching s | assembly s | "
              "triangulation s | SIFT x 1 worker | matching x 1 worker | SIFT + matching x 1 worker | points | "
              "same database | peak MiB per worker | peak MiB, client |")
        print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- | ---: | ---: |")
        for r in rows:
            one = next(b for b in rows if b["images"] == r["images"] and b["workers"] == 1)
            both = (one["sift"] + one["matching"]) / (r["sift"] + r["matching"])
            print(f"| | {r['images']} | {r['workers']} | {r['sift']:.1f} | {r['matching']:.1f} | {r['assembly']:.1f} "
                  f"| {r['triangulation']:.1f} | {one['sift'] / r['sift']:.2f} | {one['matching'] / r['matching']:.2f} "
                  f"| {both:.2f} | {r['points']} | {same_database(one['database'], r['database'])} | "
                  f"{r['worker_peak_mib']:.0f} | {r['client_peak_mib']:.0f} |")
        print("goal: SIFT and matching with 2 workers at least 1.8 x the speed of 1; the same database")
    if "sfm" in args.parts:
        rows = sfm_rows(args)
        (args.work / "sfm-rows.json").write_text(json.dumps(rows, indent=1))
        print("\n| SfM | scene | mapper | images | registered | points | mapping s | x incremental | position error "
              "(% of scale) | rotation error (deg) |")
        print("| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
        for r in rows:
            base = next((b for b in rows if b["scene"] == r["scene"] and b["mapper"] == "incremental"), None)
            timed = base and r.get("mapping") and base.get("mapping")
            speed = f"{base['mapping'] / r['mapping']:.1f}" if timed else "-"
            print(f"| | {r['scene']} | {r['mapper']} | {r['images']} | {r['registered']} | {r['points']} | "
                  f"{r.get('mapping', float('nan')):.1f} | {speed} | {r['position_pct']:.2f} | "
                  f"{r['rotation_deg']:.2f} |")
        print("x incremental: incremental's mapping seconds / this mapper's (above 1: faster)")
    return 0
