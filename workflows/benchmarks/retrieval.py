"""Benchmark: retrieval alone, per scene and condition, against the oracle.

The maps and queries are the accuracy benchmark's (``--work``: its maps are reused, or built) and the
demo's. A reference is **right** for a query when it sees at least ``--min-share`` of the map points
that the query's best-placed reference sees in the query's ground-truth view, and at least
``MIN_POINTS`` (co-visibility: a point counts where it projects into the query's image, in front of
it, and the two viewing rays meet it at less than ``MAX_ANGLE`` degrees, so that a map image of the
other side of an object does not count). Per scene, condition and method: recall@1/5/10 (a right
reference in the top k, over the queries that have one), the median rank of the top-1 among the map
images ordered by co-visibility (1: the best-placed), time per query (its image, network pass or
SIFT, ranking; 2 CPU cores, one thread) and index bytes per map image.

Conditions: ``as-taken`` (the queries' own images, the demo's day/dusk/night/occluded by their tag)
and ``relit``: each query relit to night by the training's photometric change
(``pipeline.data.photo_pairs.night_change``, seeded per query), written once in ``--work``.
Methods: the ``RETRIEVERS`` entries ``global`` (the store's descriptor), ``bow`` (the map's SIFT,
``pipeline.localization.bow``), ``fusion`` (both, by reciprocal rank), and ``oracle`` (the order
of co-visibility itself: recall 100 % wherever a right reference exists).
"""

import argparse
import dataclasses
import time
from pathlib import Path
from typing import Dict, List

import numpy as np

from pipeline.evaluate import fmt
from pipeline.descriptors import DESCRIPTORS, GeM, WhitenedGeM
from pipeline.mapping.features import FeatureConfig
from pipeline.localization.retrieval import RETRIEVERS, Fusion, GlobalDescriptors, SiftWords, retrieve
from pipeline.queries import QueryRecord
from pipeline.runtime import shared_folder

MAX_ANGLE = 60.0  # degrees between the query's and the reference's rays to a co-visible point
MIN_POINTS = 10
METHODS = (GlobalDescriptors.name, WhitenedGeM.name, SiftWords.name, Fusion.name, "oracle")
CONDITIONS = ("as-taken", "relit")
KS = (1, 5, 10)


def add_arguments(p: argparse.ArgumentParser) -> None:
    from .accuracy import SCENES
    p.add_argument("--shared", type=Path, default=shared_folder(),
                   help="the shared data folder (default: $PIXLOC_SHARED, else ../shared)")
    p.add_argument("--work", type=Path, default=Path("outputs/benchmark-accuracy"),
                   help="the accuracy benchmark's work folder: its maps are reused (or built there)")
    p.add_argument("--scenes", nargs="+", default=["demo", *SCENES], choices=["demo", *SCENES],
                   help="scenes: the demo's (its conditions by tag) and the accuracy benchmark's")
    p.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS,
                   help="retrieval methods (oracle: the order of co-visibility, the upper bound)")
    p.add_argument("--conditions", nargs="+", default=list(CONDITIONS), choices=CONDITIONS,
                   help="as-taken: the queries' own images; relit: relit to night by the training's change")
    p.add_argument("--min-share", type=float, default=0.25,
                   help="a right reference sees at least this share of the best-placed one's co-visible points")
    p.add_argument("--descriptor", choices=tuple(DESCRIPTORS), default=FeatureConfig().descriptor,
                   help="the maps' global descriptor (global); with gem, the row gem-lw whitens the stored "
                        "descriptors and the query's (default: build-map's)")
    p.add_argument("--whitening", default="",
                   help="gem-lw: the whitening file (pixloc train-whitening; default: the shipped one)")
    p.add_argument("--sift", type=int, default=0, metavar="N",
                   help="maps that store SIFT extracted at N px (build-map --sift), which bow indexes "
                        "(default 0: none; their SIFT is then extracted from the map images)")
    p.add_argument("--rank-references", type=int, default=10_000, metavar="N",
                   help="also time the global ranking of a query against N random references (0: not)")
    p.add_argument("--limit", type=int, default=0, help="at most this many queries per map (a quick look)")


def covisible(reader, query: QueryRecord) -> np.ndarray:
    """Per map image, how many of its points the query sees at its ground-truth pose (see the module)."""
    T = np.asarray(query.cam_from_world_gt, np.float64)
    cam = reader.xyz @ T[:, :3].T + T[:, 3]
    z = np.maximum(cam[:, 2], 1e-9)
    f, (cx, cy) = query.camera.focals(), query.camera.principal_point()  # lens distortion left out
    uv = np.stack([f[0] * cam[:, 0] / z + cx, f[-1] * cam[:, 1] / z + cy], 1)
    seen = (cam[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < query.camera.width) & (uv[:, 1] >= 0) \
        & (uv[:, 1] < query.camera.height)
    centre = -T[:, :3].T @ T[:, 3]
    ray = reader.xyz - centre
    ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-12)
    cos_max = np.cos(np.radians(MAX_ANGLE))
    out = np.zeros(len(reader.names))
    for i in range(len(reader.names)):
        if not reader.usable(i):
            continue
        points = reader.image_points(i)
        points = points[points >= 0]
        points = points[seen[points]]
        R, t = reader.cam_from_world[i][:, :3], reader.cam_from_world[i][:, 3]
        theirs = reader.xyz[points] + R.T @ t
        theirs /= np.maximum(np.linalg.norm(theirs, axis=1, keepdims=True), 1e-12)
        out[i] = np.count_nonzero((theirs * ray[points]).sum(1) > cos_max)
    return out


def relit(queries: List[QueryRecord], folder: Path) -> List[QueryRecord]:
    """The queries relit to night (``night_change``, seeded by the query's name), written once."""
    import zlib

    import cv2

    from pipeline.data.photo_pairs import night_change
    from pipeline.images import read_image
    from pipeline.textfiles import write_atomic
    out = []
    for q in queries:
        path = folder / (q.name.replace("/", "__") + ".jpg")
        if not path.exists():
            folder.mkdir(parents=True, exist_ok=True)
            rgb = read_image(q.path).astype(np.float32) / 255
            night = night_change(rgb, np.random.default_rng(zlib.crc32(q.name.encode())))
            ok, jpeg = cv2.imencode(".jpg", cv2.cvtColor((night * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR),
                                    [cv2.IMWRITE_JPEG_QUALITY, 95])
            write_atomic(path, jpeg.tobytes())
        out.append(dataclasses.replace(q, path=path, tags={**q.tags, "condition": "relit"}))
    return out


def maps(args, fconf, built_s: Dict[str, float]) -> List:
    """(scene, map name, store, queries) of every chosen scene; ``built_s``: the seconds that building
    each scene's maps took, where this call built them (split evenly between a scene's maps)."""
    from .accuracy import scene_parts
    from .verification import demo_map
    out = []
    for key in args.scenes:
        new = not any(args.work.glob(f"{key}*.zarr"))
        t0 = time.perf_counter()
        parts = list(demo_map(args.work, fconf)) if key == "demo" else scene_parts(key, args, fconf)
        if new:
            built_s.update({name: (time.perf_counter() - t0) / len(parts) for name, _, _ in parts})
        out += [(key, name, store, [q for q in queries if q.cam_from_world_gt is not None][:args.limit or None])
                for name, store, queries in parts]
    return out


def index_line(name: str, reader, build_s) -> str:
    """What the map's bow index took to build (its SIFT, then vocabulary and inverted file), beside the map's
    build where this run built it."""
    from pipeline.localization.bow import index_for
    index = index_for(reader)
    stored = reader.sift_descriptors(int(index.images[0])) is not None
    total = index.seconds["descriptors"] + index.seconds["index"]
    return (f"{name}: bow index of {len(index.images)} map images: {index.seconds['descriptors']:.1f} s of SIFT "
            f"({'stored' if stored else 'extracted'}), {index.seconds['index']:.1f} s of vocabulary and inverted "
            f"file ({len(index.words)} words)" + (f"; the map's build: {build_s:.1f} s ({100 * total / build_s:.0f} %)"
                                                    if build_s else ""))


def index_bytes(reader, method: str) -> float:
    """Bytes of the method's index per map image."""
    from pipeline.localization.bow import index_for
    per = {GlobalDescriptors.name: lambda: reader.global_descriptors.nbytes / len(reader.names),
           WhitenedGeM.name: lambda: reader.global_descriptors.nbytes / len(reader.names),
           SiftWords.name: lambda: index_for(reader).nbytes() / max(len(index_for(reader).images), 1)}
    if method == Fusion.name:
        return per[GlobalDescriptors.name]() + per[SiftWords.name]()
    return per[method]() if method in per else 0.0


def evaluate_map(reader, localizer, queries: List[QueryRecord], methods, min_share: float, whitening: str = ""
                 ) -> Dict:
    """Per method: the right reference's ranks (None: no right one in the ranking), the top-1's
    co-visibility rank, and seconds per query."""
    from pipeline.localization.refine import QueryCache
    from pipeline.localization.shard import describer, fit_query
    if WhitenedGeM.name in methods and reader.conf.descriptor != GeM.name:
        methods = [m for m in methods if m != WhitenedGeM.name]  # a store of another descriptor: nothing to whiten
    out = {m: {"hits": [], "top1_rank": [], "seconds": 0.0, "no_right": 0} for m in methods}
    from pipeline.descriptors import whiten
    whitened = whiten(reader.global_descriptors, whitening) if WhitenedGeM.name in methods else None  # once per map
    for q in queries:
        counts = covisible(reader, q)
        best = counts.max(initial=0)
        right = counts >= max(MIN_POINTS, min_share * best)
        order = np.argsort(-counts, kind="stable")
        rank_of = np.empty(len(counts), np.int64)
        rank_of[order] = np.arange(1, len(counts) + 1)
        for m in methods:
            t0 = time.perf_counter()
            if m == "oracle":
                dbs = [int(i) for i in order[:max(KS)] if reader.usable(i)]
            elif m == WhitenedGeM.name:  # the store's gem descriptors and the query's, whitened here
                q_fit, rgb = fit_query(q)
                sim = whitened @ whiten(describer(reader, localizer, rgb, QueryCache())(), whitening)
                dbs = [int(i) for i in np.argsort(-sim, kind="stable") if reader.usable(i)][:max(KS)]
            else:
                q_fit, rgb = fit_query(q)
                conf = RETRIEVERS.entry(m)(k=max(KS))
                dbs = retrieve(conf, reader, q_fit, describer(reader, localizer, rgb, QueryCache())).dbs
            out[m]["seconds"] += time.perf_counter() - t0
            if not right.any():
                out[m]["no_right"] += 1
                continue
            hit = [k for k, i in enumerate(dbs) if right[i]]
            out[m]["hits"].append(hit[0] + 1 if hit else None)
            out[m]["top1_rank"].append(int(rank_of[dbs[0]]) if dbs else len(counts))
    return out


def rows_for(scene: str, condition: str, per_method: Dict, bytes_per_image: Dict) -> List[Dict]:
    rows = []
    for m, v in per_method.items():
        hits = v["hits"]
        n = len(hits)
        rows.append({"scene": scene, "condition": condition, "method": m, "queries": n, "no_right": v["no_right"],
                     **{f"r@{k}": (sum(h is not None and h <= k for h in hits) / n if n else None) for k in KS},
                     "top1_rank": float(np.median(v["top1_rank"])) if v["top1_rank"] else None,
                     "ms": 1000 * v["seconds"] / max(n + v["no_right"], 1), "bytes": bytes_per_image.get(m)})
    return rows


def pooled(rows: List[Dict]) -> List[Dict]:
    """Per condition and method over all scenes (recalls weighted by queries)."""
    out = []
    for cond in dict.fromkeys(r["condition"] for r in rows):
        for m in dict.fromkeys(r["method"] for r in rows):
            mine = [r for r in rows if r["condition"] == cond and r["method"] == m and r["queries"]]
            n = sum(r["queries"] for r in mine)
            if not n:
                continue
            out.append({"scene": "all", "condition": cond, "method": m, "queries": n,
                        "no_right": sum(r["no_right"] for r in mine),
                        **{f"r@{k}": sum(r[f"r@{k}"] * r["queries"] for r in mine) / n for k in KS},
                        "top1_rank": None, "ms": sum(r["ms"] * r["queries"] for r in mine) / n,
                        "bytes": None})
    return out


def table(rows: List[Dict]) -> str:
    lines = ["| scene | condition | method | queries (none right) | " + " | ".join(f"recall@{k}" for k in KS)
             + " | median rank of top-1 | ms / query | index B / image |",
             "| --- | --- | --- | ---: | " + " | ".join("---:" for _ in KS) + " | ---: | ---: | ---: |"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['condition']} | {r['method']} | {r['queries']} ({r['no_right']}) | "
                     + " | ".join("-" if r[f"r@{k}"] is None else f"{100 * r[f'r@{k}']:.0f} %" for k in KS)
                     + f" | {fmt(r['top1_rank'], '.0f')} | {fmt(r['ms'], '.0f')} | {fmt(r['bytes'], '.0f')} |")
    return "\n".join(lines)


def main(args: argparse.Namespace) -> int:
    import json

    from pipeline.localization.refine import Localizer, LocalizerConfig
    from pipeline.models import localization_model
    from pipeline.runtime import torch_threads
    from pipeline.store.info import feature_configs
    from pipeline.store.reader import MapReader
    from pixloc.nets.registry import DEFAULT_MODEL

    from .accuracy import SPLITS  # noqa: F401  (the scenes' splits, as the accuracy benchmark has them)
    args.resize, args.dtype, args.pca, args.model = 512, "int8", None, DEFAULT_MODEL
    fconf = FeatureConfig(model=DEFAULT_MODEL, resize=512, image_scales=(1,), dtype="int8", descriptor=args.descriptor,
                          sift=args.sift)
    args.work.mkdir(parents=True, exist_ok=True)
    found: Dict = {}  # (scene, condition) -> per method, over the scene's maps
    sizes: Dict = {}
    with torch_threads(1):
        refiner, digest = localization_model(DEFAULT_MODEL, "cpu")
        built_s: Dict[str, float] = {}  # seconds of each map's build, where this run built it
        for scene, name, store, queries in maps(args, fconf, built_s):
            configs = feature_configs(store)  # the benchmark's descriptor where the store has several groups
            conf = next((c for c in configs if c.descriptor == fconf.descriptor), configs[0])
            reader = MapReader(store, conf, digest)
            localizer = Localizer(refiner.extractor, refiner.solvers, reader, LocalizerConfig(), "cpu")
            sizes[scene] = {m: index_bytes(reader, m) for m in args.methods}
            if SiftWords.name in args.methods or Fusion.name in args.methods:
                print(index_line(name, reader, built_s.get(name)), flush=True)
            for condition in args.conditions:
                if condition == "relit":
                    groups = {"relit": relit(queries, args.work / "relit" / name)}
                else:
                    groups = {}
                    for q in queries:
                        groups.setdefault(q.tags.get("condition", "as-taken") if scene == "demo" else "as-taken",
                                          []).append(q)
                for cond, qs in groups.items():
                    merge(found.setdefault((scene, cond), {}),
                          evaluate_map(reader, localizer, qs, args.methods, args.min_share, args.whitening))
            print(table([r for (s, c), v in found.items() if s == scene for r in rows_for(s, c, v, sizes[s])]),
                  flush=True)
    rows = [r for (s, c), v in found.items() for r in rows_for(s, c, v, sizes[s])]
    rows += pooled([r for r in rows if r["scene"] != "demo"])
    print("\n" + table(rows))
    (args.work / "retrieval-rows.json").write_text(json.dumps(rows, indent=1))
    if args.rank_references:
        print(f"\nglobal ranking of one query against {args.rank_references} references (gem-lw, 128 float32 each, "
              f"one core, the network pass not counted): {ranking_ms(args.rank_references):.1f} ms")
    return 0


def ranking_ms(n: int, repeats: int = 20) -> float:
    """Milliseconds to rank n random unit descriptors for one query (``global_ranking``, as ``global`` does)."""
    from types import SimpleNamespace

    from pipeline.descriptors import whiten
    from pipeline.localization.retrieval import global_ranking
    rng = np.random.default_rng(0)
    d = whiten(rng.normal(size=(n, 128)).astype(np.float32))
    reader = SimpleNamespace(names=[str(i) for i in range(n)], global_descriptors=d, usable=lambda i: True)
    t0 = time.perf_counter()
    for k in range(repeats):
        global_ranking(reader, d[k], 10)
    return 1000 * (time.perf_counter() - t0) / repeats


def merge(into: Dict, found: Dict) -> None:
    """Adds one map's results per method to a scene's."""
    for m, v in found.items():
        o = into.setdefault(m, {"hits": [], "top1_rank": [], "seconds": 0.0, "no_right": 0})
        o["hits"] += v["hits"]
        o["top1_rank"] += v["top1_rank"]
        o["seconds"] += v["seconds"]
        o["no_right"] += v["no_right"]
