"""Benchmark: accuracy over every posed real scene of the shared data, per prior, against the SIFT + PnP peer.

Each scene is split the same way on every run (``SPLITS``): of its posed images in name order, every
``every``-th one is a query (from the second, so that the first and last stay in the map; with two
folds, the other images are the queries of a second map), and the map is built from the rest with
their known poses (SIFT triangulated, RGB-D frames, or an SfM model without the queries'
observations). Three scenes keep the splits they have elsewhere: 7-Scenes its official one
(sequences 1 and 4 against 2 and 3), Sacre Coeur the oracle's three day photos (each against the
other nine) and its night photo, virtual_gallery its kapture queries.

Every query is localized with each prior (``top1``, ``search``, ``sift``) from retrieval, with
verification on; the reported pose is the refined one where verified, else the prior. Beside them:
``sift-pnp``, the peer (the sift runs' PnP poses alone; no pose where PnP failed) and
``reference``, the top-1 reference's pose unrefined (the prior itself). Per scene and row: recall at
thresholds relative to the scene's scale, its median camera-to-point distance (1 %, 1 deg; 5 %,
2 deg; 10 %, 5 deg), and at (5 cm, 1 deg) and (25 cm, 2 deg) where the scene is metric; median
errors; the poses reported as successes and how many of them are wrong (beyond 10 %, 5 deg); and
time per query (the wall time of the runs; the peer's is the sift runs' time before the LM: image,
retrieval, SIFT and PnP). Runs are kept in ``--work``: a rerun reprints. ``--model`` runs another feature
model (its own ``--work``), and ``--paired WORK`` compares the run query by query with another one (how a
candidate model is judged against the shipped one: docs/model_card.md).
"""

import argparse
import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Tuple

import numpy as np

from pipeline.descriptors import DESCRIPTORS
from pipeline.runtime import shared_folder
from pipeline.evaluate import fmt, record_errors, usable_ground_truth
from pipeline.localization.refine import LocalizerConfig
from pipeline.localization.priors import Search, Sift, Top1
from pipeline.localization.retrieval import RETRIEVERS, Fusion, GlobalDescriptors, SiftWords
from pipeline.mapping.features import COMPACT_PCA, DTYPES, FeatureConfig
from pipeline.mapping.readers.colmap import run_sfm
from pipeline.store.reader import MapReader
from pixloc.nets.registry import DEFAULT_MODEL

from ..build_map import plan_build, run_sync as build_sync
from ..evaluate_model import comparison_lines, sign_test
from pipeline.mapping.readers.sources import MapSource, as_query, load_scene
from .sacre_coeur import sacre_coeur
from .search import SACRE_COEUR_FEATURES, SIFT_VARIANTS, localize_priors, virtual_gallery_map
from .verification import seven_scenes_map, store_complete

RELATIVE = ((0.01, 1.0), (0.05, 2.0), (0.10, 5.0))  # (fraction of the scene's scale, degrees)
METRIC = ((0.05, 1.0), (0.25, 2.0))  # (metres, degrees), where the scene is metric
PRIORS = (Top1.name, Search.name, Sift.name)  # the benchmark's rows: from retrieval, the search, SIFT + PnP


@dataclass(frozen=True)
class Split:
    """A scene's fixed split: of the posed images of ``source`` in name order, fold f holds out
    every ``every``-th one from image 1 + f as queries; the map is the rest."""

    source: MapSource
    every: int = 2
    folds: int = 1
    metric: bool = False


def load_splits() -> Dict[str, Split]:
    """The scenes with a fixed split, as data (``scenes.yaml`` beside this module)."""
    from importlib import resources
    from pipeline.textfiles import read_yaml
    path = Path(str(resources.files(__package__) / "scenes.yaml"))
    out = {}
    for key, scene in read_yaml(path, "benchmark scenes").items():
        source = dict(scene.pop("source"))
        source = MapSource(source.pop("kind"), Path(source.pop("path")),
                           Path(source.pop("images")) if "images" in source else None,
                           **{k: tuple(v) if isinstance(v, list) else v for k, v in source.items()})
        out[key] = Split(source, **scene)
    return out


SPLITS: Dict[str, Split] = load_splits()
# the scenes that keep the splits they have in other benchmarks, and whether each is metric
OWN_SPLITS = {"7scenes": True, "sacre_coeur": False, "virtual_gallery": True}
SCENES = ("fountain", "herzjesus", "7scenes", "sacre_coeur", "virtual_gallery", *list(SPLITS)[2:])


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--shared", type=Path, default=shared_folder(),
                   help="the shared data folder (default: $PIXLOC_SHARED, else ../shared)")
    p.add_argument("--work", type=Path, default=Path("outputs/benchmark-accuracy"), help="maps and runs")
    p.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES, help="scenes to run")
    p.add_argument("--priors", nargs="+", default=list(PRIORS), choices=PRIORS + tuple(SIFT_VARIANTS),
                   help="priors (sift adds the peer row sift-pnp; top1 the row reference, its start unrefined); "
                        "sift-features, sift-gate, sift-joint-gate: sift without its refinement's keypoint term, "
                        "with the gate (verification's --max-keypoint-chi2), or both")
    p.add_argument("--resize", type=int, default=512,
                   help="longer image side of the maps' and queries' features (7-Scenes: 320, Sacre Coeur: "
                        "1024 with image scales 4 1, as in the other benchmarks, whatever this says)")
    p.add_argument("--sift", type=int, default=0, metavar="N",
                   help="maps that store SIFT descriptors extracted at N px (build-map --sift), which the sift "
                        "prior then matches instead of extracting the references' (default 0: none)")
    p.add_argument("--descriptor", choices=tuple(DESCRIPTORS), default=FeatureConfig().descriptor,
                   help="the maps' global descriptor for retrieval (default: build-map's)")
    p.add_argument("--retrieval", choices=(GlobalDescriptors.name, SiftWords.name, Fusion.name),
                   default=GlobalDescriptors.name, help="the retrieval method of every run (its runs kept apart)")
    p.add_argument("--dtype", choices=DTYPES, default=FeatureConfig.dtype,
                   help="feature storage of the maps (the build-map default: the compact store)")
    p.add_argument("--pca", type=int, metavar="D", help="principal components per level (build-map's default: "
                   f"{COMPACT_PCA} with int8, else 0)")
    p.add_argument("--against", type=Path, metavar="WORK",
                   help="another work folder of this benchmark (other feature storage): its rows and its maps' bytes "
                        "per observation side by side with this run's")
    p.add_argument("--model", default=DEFAULT_MODEL,
                   help=f"the feature model of the maps and queries (default {DEFAULT_MODEL}; one --work per model)")
    p.add_argument("--paired", type=Path, metavar="WORK",
                   help="another work folder of this benchmark (e.g. another model's): query by query against it, "
                        "per scene and prior, with the sign test and the queries gained and lost")
    p.add_argument("--limit", type=int, default=0,
                   help="at most this many queries per scene and fold (a quick look; runs kept apart)")


def held_out(names: List[str], every: int, fold: int) -> List[str]:
    """The split's queries: every ``every``-th name in order, from the (1 + fold)-th."""
    return sorted(names)[(1 + fold) % every::every]


def _posed(key: str, split: Split, shared: Path, work: Path):
    """The scene's posed images (the ground truth) and, for an SfM source, its whole model."""
    source = dataclasses.replace(split.source, path=shared / split.source.path,
                                 images=shared / split.source.images if split.source.images else None)
    if source.format.queries:  # a source of posed images: a split of them
        return source, source.format.images(source), None
    model = run_sfm(source.path, work / f"{key}.sfm")  # the map is this model without the queries' observations
    return source, model.images, model


def split_parts(key: str, split: Split, shared: Path, work: Path, fconf: FeatureConfig, limit: int = 0
                ) -> Iterator[Tuple[str, Path, List]]:
    """(name, store, queries) for each fold of the scene; a finished map is reused."""
    source, images, model = _posed(key, split, shared, work)
    for fold in range(split.folds):
        held = set(held_out([im.name for im in images], split.every, fold))
        name = f"{key}-{fold + 1}of{split.every}"  # another split is another map, never a finished one reused
        store = work / f"{name}.zarr"
        if not store_complete(store, fconf):
            if model is not None:
                scene = model.subset([i for i, im in enumerate(model.images) if im.name not in held])
            else:
                scene = load_scene(dataclasses.replace(source, hold_out=tuple(sorted(held))), work / f"{name}.work")
            build_sync(plan_build(scene, store, fconf))
        queries = [as_query(im) for im in images if im.name in held]
        yield name, store, queries[:limit or None]


def scene_parts(key: str, args, fconf: FeatureConfig) -> List[Tuple[str, Path, List]]:
    if key == "7scenes":
        parts = list(seven_scenes_map(args.shared, args.work, fconf))
    elif key == "sacre_coeur":
        features = dataclasses.replace(SACRE_COEUR_FEATURES, model=fconf.model, dtype=fconf.dtype, pca=fconf.pca,
                                       descriptor=fconf.descriptor)
        parts = sacre_coeur(args.shared, args.work, features)
    elif key == "virtual_gallery":
        parts = list(virtual_gallery_map(args.shared, args.work, fconf))
    else:
        return list(split_parts(key, SPLITS[key], args.shared, args.work, fconf, args.limit))
    return [(name, store, queries[:args.limit or None]) for name, store, queries in parts]


def scene_scale(store: Path) -> float:
    """The map's median camera-to-point distance over its observations."""
    from pipeline.store.info import feature_configs
    reader = MapReader(store, feature_configs(store)[0])  # poses and points: any feature group opens them
    distances = []
    for i in range(len(reader.names)):
        R, t = reader.cam_from_world[i][:, :3], reader.cam_from_world[i][:, 3]
        distances.append(np.linalg.norm(reader.xyz[reader.image_points(i)] + R.T @ t, axis=1))
    return float(np.median(np.concatenate(distances)))


def row(scene: str, prior: str, records: List[Dict], gt: Dict, scale: float, metric: bool,
        seconds: Optional[float]) -> Dict:
    """One line of the table: recalls, medians, accepted and wrongly accepted poses, time."""
    gt, _ = usable_ground_truth(gt)
    by_name = {r["name"]: r for r in records}
    errors = {n: record_errors(by_name.get(n), T) for n, T in gt.items()}
    result = np.array([e["result"] for e in errors.values()]).reshape(-1, 2)
    start = np.array([e["prior"] for e in errors.values()]).reshape(-1, 2)
    t_max, r_max = RELATIVE[-1]
    wrong = [n for n, e in errors.items() if by_name.get(n, {}).get("success")
             and not (e["result"][0] < t_max * scale and e["result"][1] < r_max)]

    def recall(t, r):
        return float(np.mean((result[:, 0] < t) & (result[:, 1] < r))) if len(result) else None

    def median(e, k):
        finite = e[np.isfinite(e).all(1)]
        return float(np.median(finite[:, k])) if len(finite) else None
    med_t, start_t = median(result, 0), median(start, 0)
    return {"scene": scene, "prior": prior, "queries": len(result), "scale": scale,
            "start_t_pct": None if start_t is None else 100 * start_t / scale, "start_R": median(start, 1),
            **{f"{100 * f:g} %, {r:g} deg": recall(f * scale, r) for f, r in RELATIVE},
            **{f"{t:g} m, {r:g} deg": recall(t, r) if metric else None for t, r in METRIC},
            "median_t_pct": None if med_t is None else 100 * med_t / scale, "median_R": median(result, 1),
            "accepted": None if prior in ("sift-pnp", "reference") else sum(bool(r.get("success")) for r in records),
            "wrong": None if prior in ("sift-pnp", "reference") else wrong,
            "s_per_query": None if seconds is None else seconds / max(len(records), 1),
            # per query: translation error as a fraction of the scale, rotation error (None: no pose)
            "errors": {n: [e["result"][0] / scale, e["result"][1]] if np.isfinite(e["result"]).all() else None
                       for n, e in errors.items()}}


TIE = 1e-4  # translation errors closer than this fraction of the scene's scale are a tie


def paired(rows: List[Dict], baseline: List[Dict]) -> List[Dict]:
    """Query by query against ``baseline`` (the rows of another run, e.g. another model), per scene and
    prior and pooled per prior: queries that end closer or farther (translation, relative to the scale;
    no pose counts as the worst), the sign test of the two, and queries gained or lost at each relative
    threshold."""
    base = {(r["scene"], r["prior"]): r.get("errors") for r in baseline}
    out, pools = [], {}
    for r in rows:
        theirs = base.get((r["scene"], r["prior"]))
        if not r.get("errors") or not theirs or r["scene"] == "all":
            continue
        names = sorted(set(r["errors"]) & set(theirs))
        worst = [math.inf, math.inf]
        pair = [(theirs[n] or worst, r["errors"][n] or worst) for n in names]
        pools.setdefault(r["prior"], []).extend(pair)
        out.append(_compare(r["scene"], r["prior"], pair))
    return out + [_compare("all", prior, pair) for prior, pair in pools.items()]


def _compare(scene: str, prior: str, pair: List) -> Dict:
    closer = sum(b[0] < a[0] - TIE for a, b in pair)
    farther = sum(b[0] > a[0] + TIE for a, b in pair)
    out = {"scene": scene, "prior": prior, "queries": len(pair), "closer": closer, "farther": farther,
           "sign_test_p": sign_test(closer, farther)}
    for f, deg in RELATIVE:
        within = lambda e: e[0] < f and e[1] < deg
        out[f"{100 * f:g} %, {deg:g} deg"] = (sum(within(b) and not within(a) for a, b in pair),
                                             sum(within(a) and not within(b) for a, b in pair))
    return out


def paired_table(comparison: List[Dict], baseline: str) -> str:
    keys = [f"{100 * f:g} %, {r:g} deg" for f, r in RELATIVE]
    rows = [(c["scene"], c["prior"], c["queries"], c["closer"], c["farther"], c["sign_test_p"], [c[k] for k in keys])
            for c in comparison]
    return "\n".join([f"Query by query against {baseline} (closer / farther: translation error, ties within "
                      f"{100 * TIE:g} % of the scale; gained / lost: queries brought within or taken out of a "
                      "threshold):", ""] + comparison_lines(("scene", "prior", "queries"), keys, rows))


RECALLS = [f"{100 * f:g} %, {r:g} deg" for f, r in RELATIVE] + [f"{t:g} m, {r:g} deg" for t, r in METRIC]


def pooled(rows: List[Dict]) -> List[Dict]:
    """The rows of each prior over all scenes: recalls weighted by queries, accepted and wrong summed."""
    out = []
    for prior in dict.fromkeys(r["prior"] for r in rows):
        mine = [r for r in rows if r["prior"] == prior]
        n = sum(r["queries"] for r in mine)

        def weighted(k, rs):
            rs = [r for r in rs if r[k] is not None]
            return sum(r[k] * r["queries"] for r in rs) / max(sum(r["queries"] for r in rs), 1) if rs else None
        accepted = None if mine[0]["accepted"] is None else sum(r["accepted"] for r in mine)
        out.append({"scene": "all", "prior": prior, "queries": n, "scale": None, "start_t_pct": None,
                    "start_R": None, **{k: weighted(k, mine) for k in RECALLS}, "median_t_pct": None,
                    "median_R": None, "accepted": accepted,
                    "wrong": None if accepted is None else [w for r in mine for w in r["wrong"]],
                    "s_per_query": weighted("s_per_query", [r for r in mine if r["s_per_query"] is not None])})
    return out


def table(rows: List[Dict]) -> str:
    lines = ["| scene | prior | queries | start: median t (% of scale), R | "
             + " | ".join(RECALLS) + " | median t (%), R | successes (wrong) | s / query |",
             "| --- | --- | ---: | --- | " + " | ".join("---:" for _ in RECALLS) + " | --- | ---: | ---: |"]
    for r in rows:
        start = "" if r["start_R"] is None else f"{fmt(r['start_t_pct'], '.1f')} %, {fmt(r['start_R'], '.1f')} deg"
        med = "" if r["median_R"] is None and r["scene"] == "all" else \
            f"{fmt(r['median_t_pct'], '.2f')} %, {fmt(r['median_R'], '.2f')} deg"
        acc = "-" if r["accepted"] is None else f"{r['accepted']} ({len(r['wrong'])})"
        lines.append(f"| {r['scene']} | {r['prior']} | {r['queries']} | {start} | "
                     + " | ".join("-" if r[k] is None else f"{100 * r[k]:.0f} %" for k in RECALLS)
                     + f" | {med} | {acc} | {fmt(r['s_per_query'], '.2f')} |")
    return "\n".join(lines)


def goals(rows: List[Dict]) -> List[str]:
    """The issue's goals, each with the scenes that miss it."""
    key = RECALLS[1]  # (5 %, 2 deg)
    get = {(r["scene"], r["prior"]): r for r in rows}
    scenes = [s for s in dict.fromkeys(r["scene"] for r in rows) if s != "all"]
    peer_good = [s for s in scenes if (s, "sift-pnp") in get and (get[s, "sift-pnp"][key] or 0) >= 0.9]
    out = []
    for prior, goal in ((Sift.name, 0.95), (Search.name, 0.80)):
        if not peer_good or not all((s, prior) in get for s in peer_good):
            continue
        miss = [f"{s} {100 * get[s, prior][key]:.0f} %" for s in peer_good if get[s, prior][key] < goal]
        out.append(f"{prior} >= {100 * goal:.0f} % at ({key}) on the {len(peer_good)} scenes where the peer "
                   f"reaches 90 %: {'met' if not miss else 'missed on ' + ', '.join(miss)}")
    both = [s for s in scenes if (s, "sift") in get and (s, "sift-pnp") in get]
    if both:
        tight = RECALLS[0]
        below = [f"{s} {100 * get[s, 'sift'][tight]:.0f} % < {100 * get[s, 'sift-pnp'][tight]:.0f} %" for s in both
                 if get[s, "sift"][tight] < get[s, "sift-pnp"][tight]]
        closer = [s for s in both if None not in (get[s, "sift"]["median_t_pct"], get[s, "sift-pnp"]["median_t_pct"])
                  and get[s, "sift"]["median_t_pct"] < get[s, "sift-pnp"]["median_t_pct"]]
        out.append(f"sift >= the peer at ({tight}) on {len(both) - len(below)} of {len(both)} scenes"
                   f"{' (below on ' + ', '.join(below) + ')' if below else ''}; median position error lower "
                   f"than the peer's on {len(closer)} of {len(both)}{': ' + ', '.join(closer) if closer else ''}")
    accepted = sum(r["accepted"] for r in rows if r["scene"] != "all" and r["accepted"] is not None)
    wrong = [f"{r['scene']}/{r['prior']}: {w}" for r in rows if r["scene"] != "all" and r["wrong"] for w in r["wrong"]]
    if accepted:
        named = ", ".join(wrong[:5]) + (f" and {len(wrong) - 5} more" if len(wrong) > 5 else "")
        out.append(f"precision of success {1 - len(wrong) / accepted:.3f} ({len(wrong)} wrong of {accepted} "
                   f"accepted; goal >= 0.97){': ' + named if wrong else ''}")
    return out


def main(args: argparse.Namespace) -> int:
    fconf = FeatureConfig(model=args.model, resize=args.resize, image_scales=(1,), sift=args.sift,
                          dtype=args.dtype, pca=args.pca, descriptor=args.descriptor)
    lconf = LocalizerConfig(num_dbs=3, num_iters=50)
    args.work.mkdir(parents=True, exist_ok=True)
    settings = args.work / "features.json"  # one work folder, one feature setting: its maps hold one group
    if settings.exists() and not fconf.made(json.loads(settings.read_text())):  # as recorded by any version
        raise SystemExit(f"pixloc: error: {args.work} holds maps of features {settings.read_text().strip()}, "
                         f"not {json.dumps(fconf.to_dict())} (--resize, --sift, --dtype, --pca, --descriptor): "
                         "give another --work")
    settings.write_text(json.dumps(fconf.to_dict()) + "\n")
    runs = args.work / ("runs" + (f"-{args.retrieval}" if args.retrieval != GlobalDescriptors.name else "")
                        + (f"-limit{args.limit}" if args.limit else ""))
    rows: List[Dict] = []
    remarks = []  # scenes whose map could not be built (with the reason), the night photo's outcome
    for key in args.scenes:
        try:
            parts = scene_parts(key, args, fconf)
        except (ValueError, OSError, RuntimeError) as e:
            remarks.append(f"{key}: no map ({type(e).__name__}: {e})")
            print(f"- {remarks[-1]}", flush=True)
            continue
        scale = scene_scale(parts[0][1])
        metric = OWN_SPLITS[key] if key in OWN_SPLITS else SPLITS[key].metric
        per_prior, gt = localize_priors(parts, list(args.priors), runs, lconf, RETRIEVERS.entry(args.retrieval)(k=5),
                                        fconf.descriptor)
        if Top1.name in per_prior:  # the prior itself: the top-1 reference's pose, unrefined
            per_prior["reference"] = {"records": [dict(r, success=False) for r in per_prior[Top1.name]["records"]],
                                      "time": None}
        for prior, v in per_prior.items():
            rows.append(row(key, prior, v["records"], gt, scale, metric, v["time"]))
        if key == "sacre_coeur" and Search.name in per_prior and "night.jpg" in gt:  # the goal on the night photo
            rec = next((r for r in per_prior[Search.name]["records"] if r["name"] == "night.jpg"), None)
            t, R = record_errors(rec, gt["night.jpg"])["result"]
            within = t < RELATIVE[1][0] * scale and R < RELATIVE[1][1]
            remarks.append(f"the night photo from search: {100 * t / scale:.2f} %, {R:.2f} deg, "
                           f"{'within' if within else 'not within'} ({RECALLS[1]})")
        print(table([r for r in rows if r["scene"] == key]), flush=True)
    rows += pooled(rows)
    print("\n" + table(rows))
    for line in goals(rows) + remarks:
        print("- " + line)
    (args.work / "rows.json").write_text(json.dumps(rows, indent=1))
    if args.against:
        print()
        print(storage_table(args.work, args.against, args.scenes))
    if args.paired:
        print()
        print(paired_table(paired(rows, json.loads((args.paired / "rows.json").read_text())), str(args.paired)))
    return 1 if any(": no map (" in line for line in remarks) else 0


def store_bytes(work: Path, key: str) -> Optional[Tuple[float, float]]:
    """(store bytes, feature bytes) per observation of a scene's maps in ``work`` (every fold)."""
    from pipeline.store import location
    from pipeline.store.info import map_counts

    total = features = observations = 0
    for store in sorted(work.glob(f"{key}*.zarr")):
        observations += map_counts(store)["num_observations"]
        total += location.total_bytes(store)
        features += location.total_bytes(store / "features")
    return (total / observations, features / observations) if observations else None


def storage_name(work: Path) -> str:
    """The feature storage of a work folder's maps, as their feature groups record it."""
    from pipeline.store.info import feature_configs

    for store in sorted(work.glob("*.zarr")):
        for conf in feature_configs(store):
            return conf.dtype + (f" + PCA {conf.pca}" if conf.pca else "")
    return "unknown"


def storage_table(work: Path, against: Path, scenes) -> str:
    """This run's recall and bytes per observation against another work folder's, per scene and prior."""
    names = [storage_name(w) for w in (work, against)]
    rows = json.loads((work / "rows.json").read_text())
    other = {(r["scene"], r["prior"]): r for r in json.loads((against / "rows.json").read_text())}
    sizes = {key: [store_bytes(w, key) for w in (work, against)] for key in scenes}

    def pair(a: Dict, b: Dict, key: str, form: str = "{:.0f} %", scale: float = 100) -> str:
        return " / ".join("-" if x.get(key) is None else form.format(scale * x[key]) for x in (a, b))

    def successes(x: Dict) -> str:
        return "-" if x.get("accepted") is None else f"{x['accepted']} ({len(x['wrong'] or [])})"

    lines = [f"storage: {names[0]} ({work}) / {names[1]} ({against})", "",
             "| scene | prior | queries | " + " | ".join(f"{t} recall" for t in RECALLS) + " | median error | "
             "successes (wrong) | store B / obs | features B / obs |",
             "| --- | --- | ---: | " + " | ".join("---:" for _ in RECALLS) + " | ---: | ---: | ---: | ---: |"]
    for r in rows:
        o = other.get((r["scene"], r["prior"]))
        if o is None or r["prior"] == "reference":
            continue
        size = sizes.get(r["scene"], [None, None])
        shown = [" / ".join("-" if s is None else f"{s[i]:.0f}" for s in size) for i in (0, 1)]
        lines.append(f"| {r['scene']} | {r['prior']} | {r['queries']} | "
                     + " | ".join(pair(r, o, t) for t in RECALLS)
                     + f" | {pair(r, o, 'median_t_pct', '{:.2f} %', 1)}, {pair(r, o, 'median_R', '{:.2f} deg', 1)}"
                     + f" | {successes(r)} / {successes(o)} | {shown[0]} | {shown[1]} |")
    same = sum(all(r.get(t) == other[(r["scene"], r["prior"])].get(t) for t in RECALLS)
               for r in rows if (r["scene"], r["prior"]) in other)
    lines += ["", f"rows with the same recall at every threshold (the unrefined references and the totals "
              f"included): {same} of {len(other)}"]
    return "\n".join(lines)
