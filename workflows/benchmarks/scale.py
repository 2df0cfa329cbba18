"""Benchmark: the map store at the size of Aachen Day-Night v1.1 (S3 of docs/scaling.md).

A store of 6,697 reference images, 6.1 M points and 29.8 M observations (the Aachen v1.1
LoFTR model's counts; ``--fraction`` scales them down), written with the real layout and code
path (``create_store``, ``init_features``, ``write_image_features``: sharding, int8 codes,
checksums). Only the values are synthetic: features are Gaussian noise, which compresses worse
than real features (the worst case for bytes on disk), observation counts per image are
log-normal around the mean, and each image sees points of its own part of the map.

Then, in a fresh process: the time to open a ``MapReader``, its resident memory, and the
latency of the reads of one query (its 3 references' observations and features, cold cache),
over ``--queries`` queries. Figures are printed next to the goals of issue 12 and to the
version-2 layout (one file per 256-row chunk per array, float16), computed for the same counts.
"""

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict

import numpy as np

from pipeline.features import FeatureConfig, ImageFeatures
from pipeline.scene import CameraRecord, ImageRecord, Scene

AACHEN = {"images": 6697, "points": 6_100_000, "observations": 29_800_000}
DIMS = [32, 128, 128]
GOALS = {"bytes": 10e9, "files": 150_000, "rss": 2 * 2**30}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--work", type=Path, default=Path("outputs/benchmark-scale"))
    p.add_argument("--fraction", type=float, default=1.0, help="of the Aachen v1.1 counts (default 1: full size)")
    p.add_argument("--dtype", default="int8", choices=["int8", "float16"])
    p.add_argument("--image-scales", type=int, nargs="+", default=[1],
                   help="image scales stored (default [1]; the Aachen preset's [4, 1] doubles the features)")
    p.add_argument("--queries", type=int, default=50, help="queries whose reads are timed")
    p.add_argument("--seed", type=int, default=0)


def synthetic_scene(num_images: int, num_points: int, num_obs: int, seed: int = 0) -> Scene:
    """Images along a line of the map, each seeing points of its own stretch of it."""
    rng = np.random.default_rng(seed)
    counts = rng.lognormal(0.0, 0.6, num_images)
    counts = np.maximum(1, np.round(counts / counts.sum() * num_obs)).astype(np.int64)
    counts[np.argmax(counts)] += num_obs - counts.sum()
    camera = CameraRecord("PINHOLE", 1600, 1200, (1200.0, 1200.0, 800.0, 600.0))
    images = [ImageRecord(f"db/{i:05d}.jpg", Path(f"db/{i:05d}.jpg"), camera,
                          np.concatenate([np.eye(3), [[0.0], [0.0], [-0.5 * i]]], 1)) for i in range(num_images)]
    obs_image = np.repeat(np.arange(num_images), counts)
    centre = (obs_image + 0.5) * num_points / num_images
    window = 4 * num_points / num_images
    obs_point = np.clip(centre + rng.uniform(-window, window, len(obs_image)), 0, num_points - 1).astype(np.int64)
    obs_xy = rng.uniform(0, [1600, 1200], (len(obs_image), 2)).astype(np.float32)
    points = rng.normal(size=(num_points, 3))
    return Scene(images, points, obs_point, obs_image, obs_xy)


def build(store: Path, scene: Scene, conf: FeatureConfig, seed: int) -> Dict:
    from pipeline.store import create_store, init_features, write_image_features
    rng = np.random.default_rng(seed + 1)
    t0 = time.perf_counter()
    root = create_store(store, scene, overwrite=True)
    group = init_features(root, conf, "synthetic", DIMS)
    t1 = time.perf_counter()
    num_obs = root["images/num_obs"][:]
    for i, n in enumerate(num_obs):
        samples = {(k, level): (rng.normal(size=(n, d)).astype(np.float32), rng.uniform(0, 1, n).astype(np.float32),
                                np.ones(n, bool))
                   for k in range(len(conf.image_scales)) for level, d in enumerate(DIMS)}
        write_image_features(group, root, i, ImageFeatures(samples, rng.normal(size=DIMS[-1]).astype(np.float32)))
        if i % 500 == 0:
            print(f"  features: {i}/{len(num_obs)} images, {time.perf_counter() - t1:.0f} s", flush=True)
    t2 = time.perf_counter()
    return {"structure_s": t1 - t0, "features_s": t2 - t1, "images_per_s": len(num_obs) / (t2 - t1)}


READER = r"""
import json, sys, time, resource
import numpy as np
from pipeline.features import FeatureConfig
from pipeline.map_reader import MapReader
def rss():
    return int(open('/proc/self/status').read().split('VmRSS:')[1].split()[0]) * 1024
store, conf, queries, seed = sys.argv[1], json.loads(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
conf['image_scales'] = tuple(conf['image_scales'])
before = rss()
t0 = time.perf_counter()
reader = MapReader(store, FeatureConfig(**conf), cache_images=64)
open_s = time.perf_counter() - t0
opened = rss()
rng = np.random.default_rng(seed)
lat = []
for q in range(queries):
    i = int(rng.integers(0, len(reader.names) - 3))
    t = time.perf_counter()
    obs = reader.observations([i, i + 1, i + 2], 1)
    for k in range(len(conf['image_scales'])):
        reader.features(obs, k)
    lat.append(time.perf_counter() - t)
print(json.dumps({"open_s": open_s, "rss_before": before, "rss_open": opened, "rss_end": rss(),
                  "peak_rss": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
                  "read_ms_median": 1e3 * float(np.median(lat)), "read_ms_p90": 1e3 * float(np.quantile(lat, 0.9)),
                  "obs_per_query": int(len(obs.rows)), "bytes_read": reader.stats["bytes"], "blocks": reader.stats["blocks"]}))
"""


def v2_figures(num_obs: np.ndarray, scales: int) -> Dict:
    """The version-2 layout for the same counts: per image, ceil(n / 256) chunks of each of
    3 arrays per scale and level, and 1,047 bytes per observation (measured on the demo)."""
    chunks = np.maximum(1, -(-num_obs // 256))
    return {"files": int(chunks.sum() * 3 * len(DIMS) * scales + 3 * len(num_obs)),
            "bytes": float(num_obs.sum() * 1047 * scales)}


def main(args: argparse.Namespace) -> int:
    counts = {k: max(1, int(round(v * args.fraction))) for k, v in AACHEN.items()}
    conf = FeatureConfig(model="pixloc-lite0", image_scales=tuple(args.image_scales), dtype=args.dtype)
    store = args.work / f"aachen-{args.fraction:g}-{args.dtype}-s{'-'.join(map(str, args.image_scales))}.zarr"
    args.work.mkdir(parents=True, exist_ok=True)
    print(f"S3: a store of {counts['images']} images, {counts['points']} points, {counts['observations']} "
          f"observations ({args.fraction:g} x Aachen v1.1), {args.dtype}, image scales {args.image_scales} -> {store}")
    t0 = time.perf_counter()
    scene = synthetic_scene(counts["images"], counts["points"], counts["observations"], args.seed)
    gen_s = time.perf_counter() - t0
    built = build(store, scene, conf, args.seed)
    num_obs = np.bincount(scene.obs_image, minlength=len(scene.images))
    del scene
    files = [f for f in store.rglob("*") if f.is_file()]
    size = sum(f.stat().st_size for f in files)
    out = subprocess.run([sys.executable, "-c", READER, str(store), json.dumps(conf.to_dict()), str(args.queries),
                          str(args.seed)], capture_output=True, text=True, check=True)
    r = json.loads(out.stdout.strip().splitlines()[-1])
    v2 = v2_figures(num_obs, len(args.image_scales))
    scale = 1 / args.fraction
    rows = [("bytes on disk", f"{size / 1e9:.2f} GB", f"{size * scale / 1e9:.2f} GB", f"{v2['bytes'] * scale / 1e9:.1f} GB",
             f"<= {GOALS['bytes'] / 1e9:.0f} GB", f"{size * scale / GOALS['bytes']:.2f}"),
            ("bytes per observation", f"{size / counts['observations']:.0f}", "same", "1047 x scales", "<= 300",
             f"{size / counts['observations'] / 300:.2f}"),
            ("files", f"{len(files)}", f"{len(files) * scale:.0f}", f"{v2['files'] * scale:.0f}",
             f"<= {GOALS['files']}", f"{len(files) * scale / GOALS['files']:.2f}"),
            ("files per image", f"{len(files) / counts['images']:.1f}", "same",
             f"{v2['files'] / counts['images']:.0f}", "<= 20", f"{len(files) / counts['images'] / 20:.2f}"),
            ("time to open a reader", f"{r['open_s']:.2f} s", "", "", "", ""),
            ("reader RSS after open", f"{r['rss_open'] / 2**20:.0f} MiB (process before: "
             f"{r['rss_before'] / 2**20:.0f})", "", "", f"<= {GOALS['rss'] / 2**30:.0f} GiB per worker",
             f"{r['rss_open'] / GOALS['rss']:.2f}"),
            ("reader peak RSS (after the reads)", f"{r['peak_rss'] / 2**20:.0f} MiB", "", "", "", ""),
            ("reads of one query (3 references, cold)", f"{r['read_ms_median']:.1f} ms median, "
             f"{r['read_ms_p90']:.1f} ms p90 ({r['obs_per_query']} observations)", "", "", "", "")]
    print(f"\nscene generated in {gen_s:.0f} s; structure written in {built['structure_s']:.0f} s; features of "
          f"{counts['images']} images in {built['features_s']:.0f} s ({built['images_per_s']:.1f} images/s, 1 process)")
    print("\n| S3 | measured | at full size | v2 layout, full size | goal | measured / goal |")
    print("| --- | --- | --- | --- | --- | ---: |")
    for row in rows:
        print("| " + " | ".join(row) + " |")
    return 0
