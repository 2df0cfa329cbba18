"""Benchmark: CPU seconds per query at Cambridge settings, per speed-up, with the poses they give.

The maps are the accuracy benchmark's splits (``workflows.benchmarks.accuracy``) built at the
Cambridge settings, the official ones for Cambridge Landmarks: 1024 px, image scales [4, 1], with
the default (compact) store of the shipped model; the queries are localized from the top-1
retrieved reference with 5 references, observations averaged and 100 LM iterations per level,
verification on. Every variant runs the same queries in this process on one torch thread (as a
worker does), after an untimed pass that warms the caches. Its time is the process's CPU seconds
over the queries (image reading, retrieval, network passes, store reads and LM), with the wall
seconds of its parts: before the LM (image, retrieval with its network pass at the finest image
scale, prior), the features of the other image scale, and the LM. Its poses are compared with those
of ``today``: the network as loaded before this work (no BatchNorm folding, the default memory
layout, float32) and glibc mapping every block over 32 MiB afresh (as a worker ran before).

Variants, each adding to the one above: ``BatchNorm folded`` (into the preceding convs),
``channels-last`` activations, ``split convs, 1x1 by oneDNN`` (the decoder's convs of a concatenation
as a sum of convs, and 1x1 convs through oneDNN: ``pixloc.nets.unet.prepare_for_inference`` is these
four), ``freed memory reused`` (``pipeline.runtime.keep_freed_memory``), ``cell products`` (the LM reads
maps of few cells, the coarsest level at 256 px, through the inner products of their cells:
``pixloc.optim.cost.CellProducts``; the rows above sample them, as the code did), ``rival starts, every level``
(verification's rival starts, ``--rivals 1``: the default since 2026-12-04; the rows above run without
them, as the code did), ``rival starts, stopped where they join`` (the default from 2026-12-05: a rival
stops at a coarser level where it has reached the query's start, ``--rival-join``), ``finest level decoded
where sampled`` (with and without the rival starts: the decoder blocks that only the finest level reads run
only on the 8 x 8 px tiles that the LM and verification sample, ``pipeline.localization.finest``; the rows
above decode the whole level in the network pass), ``LM taps compiled`` (the default since 2026-12-06, with and
without the rival starts: the LM reduces the 5 bilinear taps of every level in one compiled pass per point,
``pipeline.kernels``; the rows above run its torch code, gradient maps and cell products), ``bfloat16 network``
(``--network-precision bfloat16``: reduced precision, held to the same recall at every threshold, the whole
level decoded), ``bfloat16 finest
blocks`` (``--network-precision bfloat16-fine``: only the decoder blocks that the finest level alone reads,
the coarser levels exact, its tiles decoded where sampled), with and without the rival starts;
with ``--compile``, ``torch.compile`` of the default network (inductor, dynamic shapes), in float32
and bfloat16, its one-off compile time printed apart. Also measured: the ``search`` prior's network
passes per query against its LM runs (one pass per image scale serves every start). With ``--onnx``,
one network pass is also timed in ONNX Runtime (not a dependency). With ``--earlier-code REV``, the
same queries are also run by the code of commit REV (``earlier_code``), the real baseline that ``today``
emulates, and the default's speed-up and pose differences are given against it. With ``--rounds R``, every
variant and the earlier code run R times, one round after the other, and the tables give each one's median
(the machine's drift then falls on every variant alike).
"""

import argparse
import copy
import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List

import torch
from torch import nn

from pipeline.runtime import shared_folder
from pipeline.localization.refine import Localizer, LocalizerConfig
from pipeline.localization.results import result_to_record
from pipeline.localization.priors import Search, Top1
from pipeline.localization.search import SearchConfig
from pipeline.localization.retrieval import GlobalDescriptors
from pipeline.localization.shard import LocalizationJob, localize_queries
from pipeline.mapping.features import FeatureConfig
from pipeline.runtime import native_bfloat16, set_malloc, torch_threads
from pipeline.store.reader import MapReader
from pixloc.nets.registry import DEFAULT_MODEL, load_refiner
from pixloc.nets.unet import fold_batchnorm, prepare_for_inference

from pipeline.store.info import feature_config as store_feature_config

from . import accuracy
from .earlier_code import pose_differences, run_earlier
from .sacre_coeur import sacre_coeur

CAMBRIDGE = LocalizerConfig(num_dbs=5, average_observations=True, num_iters=100)
FEATURES = FeatureConfig(model=DEFAULT_MODEL, resize=1024, image_scales=(4, 1))
SCENES = ("fountain", "herzjesus", "sacre_coeur", "kermit")


@dataclass(frozen=True)
class Variant:
    name: str
    network: Callable[[nn.Module], nn.Module]  # from a fresh copy of the loaded network
    keep_freed: bool = True  # glibc keeps freed blocks for reuse (pipeline.runtime.set_malloc)
    precision: str = "float32"
    rivals: int = 0  # verification's rival starts (the default since 2026-12-04 is 1)
    join: float = 0.5  # a rival stops where it joins the query's start (verification.join; 0: never)
    cells: bool = True  # the LM reads the coarsest maps through their cells' inner products (2026-12-05)
    tiles: bool = True  # the finest level decoded where it is sampled (pipeline.localization.finest, 2026-12-06)
    kernels: bool = True  # the LM's taps reduced by the compiled kernel (pipeline.kernels, 2026-12-06)


def _channels_last(net: nn.Module) -> nn.Module:
    """Folded and channels-last, without ``prepare_for_inference``'s 1x1 convs through oneDNN."""
    fold_batchnorm(net)
    return net.channels_last()


def _compiled(net: nn.Module) -> nn.Module:
    """Folded and channels-last, compiled (inductor makes its own 1x1 convs: oneDNN's aten op
    has no shape function for its tracing)."""
    return torch.compile(_channels_last(net), dynamic=True)


VARIANTS = [Variant("today", lambda net: net, keep_freed=False, cells=False, tiles=False, kernels=False),
            Variant("BatchNorm folded", fold_batchnorm, keep_freed=False, cells=False, tiles=False, kernels=False),
            Variant("channels-last", _channels_last, keep_freed=False, cells=False, tiles=False, kernels=False),
            Variant("split convs, 1x1 by oneDNN", prepare_for_inference, keep_freed=False, cells=False, tiles=False,
                    kernels=False),
            Variant("freed memory reused", prepare_for_inference, cells=False, tiles=False, kernels=False),
            Variant("cell products", prepare_for_inference, tiles=False, kernels=False),
            Variant("rival starts, every level", prepare_for_inference, rivals=1, join=0.0, tiles=False, kernels=False),
            Variant("rival starts, stopped where they join", prepare_for_inference, rivals=1, tiles=False,
                    kernels=False),
            Variant("finest level decoded where sampled, without rival starts", prepare_for_inference, kernels=False),
            Variant("finest level decoded where sampled", prepare_for_inference, rivals=1, kernels=False),
            Variant("LM taps compiled, without rival starts", prepare_for_inference),
            Variant("LM taps compiled (default)", prepare_for_inference, rivals=1),
            Variant("bfloat16 network", prepare_for_inference, precision="bfloat16", rivals=1),
            Variant("bfloat16 finest blocks", prepare_for_inference, precision="bfloat16-fine", rivals=1),
            Variant("bfloat16 finest blocks, without rival starts", prepare_for_inference, precision="bfloat16-fine")]
DEFAULT_VARIANT = "LM taps compiled (default)"
COMPILED = [Variant("torch.compile", _compiled, rivals=1),
            Variant("torch.compile, bfloat16", _compiled, precision="bfloat16", rivals=1)]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--shared", type=Path, default=shared_folder(),
                   help="the shared data folder (default: $PIXLOC_SHARED, else ../shared)")
    p.add_argument("--work", type=Path, default=Path("outputs/benchmark-query-cpu"), help="maps (reused)")
    p.add_argument("--scenes", nargs="+", default=list(SCENES), choices=accuracy.SCENES, help="scenes to run")
    p.add_argument("--variants", nargs="+", metavar="NAME", choices=[v.name for v in VARIANTS + COMPILED],
                   help="run only these variants (today is always run: the others are compared with it)")
    p.add_argument("--compile", action="store_true", help="also measure torch.compile (about a minute to compile)")
    p.add_argument("--limit", type=int, default=0, help="at most this many queries per map part (0: all)")
    p.add_argument("--onnx", action="store_true", help="also time the network pass in ONNX Runtime (needs the "
                   "onnxruntime and onnx packages, which the project does not depend on)")
    p.add_argument("--earlier-code", metavar="REV", help="also run the queries with the code of commit REV (a git "
                   "worktree in --work, its own process and defaults, a copy of the maps), e.g. 8975496, the code "
                   "when issue 31 was filed: the real baseline that 'today' emulates")
    p.add_argument("--rounds", type=int, default=1, help="run the variants (and the earlier code) this many times, "
                   "one round after the other, and give each one's median CPU time: the rounds spread the machine's "
                   "drift over every variant alike (its timings vary by some 20 %% between runs); 'today' emulates "
                   "the earlier code's memory settings in a fresh process only (in later rounds it ran 1.7-1.8 "
                   "against 2.5 CPU s): --earlier-code is the baseline")


def _run(variant: Variant, refiner, parts, compile_s: Dict[str, float]) -> Dict:
    """The variant's records per part, its CPU seconds and its network passes' and LM's shares."""
    net = variant.network(copy.deepcopy(refiner.extractor).eval())
    set_malloc(variant.keep_freed)
    conf = dataclasses.replace(CAMBRIDGE, network_precision=variant.precision,
                               verification=dataclasses.replace(CAMBRIDGE.verification, rivals=variant.rivals,
                                                                join=variant.join))
    solvers = copy.deepcopy(refiner.solvers)
    for solver in solvers:
        solver.interpolator.cell_products = variant.cells
    out = {"records": [], "results": [], "cpu": 0.0, "before": 0.0, "network": 0.0, "lm": 0.0}
    for name, store, queries, gt in parts:
        reader = MapReader(store, store_feature_config(store), refiner.feature_digest())
        job = LocalizationJob(str(store), reader.conf, DEFAULT_MODEL, conf, GlobalDescriptors(k=5), prior=Top1())
        localizer = Localizer(net, solvers, reader, conf, finest_on_demand=variant.tiles,
                              compiled_kernels=variant.kernels)
        with torch_threads(1):
            if variant.name not in compile_s and variant in COMPILED:
                t0 = time.perf_counter()
                localize_queries(job, reader, localizer, queries[:1])
                compile_s[variant.name] = time.perf_counter() - t0
            t0 = time.process_time()
            results = localize_queries(job, reader, localizer, queries)
            out["cpu"] += time.process_time() - t0
        for r, q in zip(results, queries):
            out["before"] += r.timings.get("prior", 0.0)
            out["network"] += sum(v for k, v in r.timings.items() if k.startswith("features_s"))
            out["lm"] += sum(v for k, v in r.timings.items() if k.startswith("optim_s"))
            out["records"].append(result_to_record(r, q.tags))
            out["results"].append(r)
    return out


def _differences(run: Dict, today: Dict, metric: Dict[str, bool]) -> Dict:
    """Largest position (mm where the scene is metric, else % of its scale) and rotation
    differences of the refined poses from today's, and the queries refined by one and not the other."""
    keys = range(len(run["results"]))
    return pose_differences({k: r.refined for k, r in zip(keys, today["results"])},
                            {k: r.refined for k, r in zip(keys, run["results"])},
                            {k: metric[scene] for k, (scene, _) in zip(keys, run["scenes"])},
                            {k: scale for k, (_, scale) in zip(keys, run["scenes"])})


def recalls(run: Dict, by_scene) -> List[float]:
    """Recall (%) at every threshold of the accuracy benchmark, pooled over the scenes (the metric
    thresholds over the metric scenes)."""
    rows = []
    for scene, (gt, scale, metric) in by_scene.items():
        records = [rec for rec, (s, _) in zip(run["records"], run["scenes"]) if s == scene]
        rows.append(accuracy.row(scene, "top1", records, gt, scale, metric, None))
    out = []
    for key in accuracy.RECALLS:
        counted = [r for r in rows if r[key] is not None]
        out.append(100 * sum(r[key] * r["queries"] for r in counted) / max(sum(r["queries"] for r in counted), 1))
    return out


def search_passes(refiner, part) -> Dict[str, float]:
    """The search prior's network passes per query against its LM starts (every start refined:
    ``first`` off): one pass per image scale serves them all."""
    net = prepare_for_inference(copy.deepcopy(refiner.extractor))
    passes, starts = [], []
    net.register_forward_hook(lambda *_: passes.append(1))
    name, store, queries, _ = part
    reader = MapReader(store, store_feature_config(store), refiner.feature_digest())
    job = LocalizationJob(str(store), reader.conf, DEFAULT_MODEL, CAMBRIDGE, GlobalDescriptors(k=5),
                          prior=Search(SearchConfig(first=False)))
    batch = Localizer.localize_batch  # counted for every Localizer, the search's screening one too
    Localizer.localize_batch = lambda self, candidates: starts.append(len(candidates)) or batch(self, candidates)
    try:
        with torch_threads(1):
            localize_queries(job, reader, Localizer(net, refiner.solvers, reader, CAMBRIDGE), queries)
    finally:
        Localizer.localize_batch = batch
    return {"runs": sum(starts) / len(queries), "passes": len(passes) / len(queries)}


class _Outputs(nn.Module):
    """The network's maps as a tuple, for the ONNX exporter."""

    def __init__(self, net: nn.Module):
        super().__init__()
        self.net = net

    def forward(self, image):
        out = self.net(image)
        return tuple(out["features"]) + tuple(out["confidences"])


def onnx_network_seconds(refiner, work: Path, size=(672, 1024)) -> Dict[str, float]:
    """One network pass at ``size`` on one thread: today's network, ours prepared, and ONNX Runtime
    running the exported (BatchNorm-folded) network with every graph optimisation; best of 3."""
    import onnxruntime

    net = refiner.extractor.eval()
    image = torch.rand(1, 3, *size)
    path = work / "network.onnx"
    torch.onnx.export(_Outputs(fold_batchnorm(copy.deepcopy(net))), (image,), str(path), dynamo=False,
                      input_names=["image"], dynamic_axes={"image": {2: "h", 3: "w"}})
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = options.inter_op_num_threads = 1
    session = onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    prepared = prepare_for_inference(copy.deepcopy(net))

    def best(fn) -> float:
        fn()
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        return min(times)
    with torch.no_grad(), torch_threads(1):
        return {"today": best(lambda: net(image)), "prepared": best(lambda: prepared(image)),
                "onnxruntime": best(lambda: session.run(None, {"image": image.numpy()}))}


def scene_parts(args: argparse.Namespace):
    """The map parts of ``args.scenes`` at the Cambridge settings in ``args.work`` (built on first use, at most
    ``args.limit`` queries each): [(name, store, queries, scene)], per scene (ground truth, scale, metric),
    per scene whether it is metric, and (scene, scale) per query in the parts' order."""
    args.work.mkdir(parents=True, exist_ok=True)
    parts, by_scene, metric = [], {}, {}
    for key in args.scenes:
        found = accuracy.scene_parts(key, args, FEATURES) if key != "sacre_coeur" else \
            sacre_coeur(args.shared, args.work, FEATURES)
        found = [(n, s, q[:args.limit or None]) for n, s, q in found]
        gt = {q.name: q.cam_from_world_gt for _, _, qs in found for q in qs}
        metric[key] = accuracy.OWN_SPLITS[key] if key in accuracy.OWN_SPLITS else accuracy.SPLITS[key].metric
        by_scene[key] = (gt, accuracy.scene_scale(found[0][1]), metric[key])
        parts += [(n, s, q, key) for n, s, q in found]
    return parts, by_scene, metric, [(key, by_scene[key][1]) for _, _, qs, key in parts for _ in qs]


def main(args: argparse.Namespace) -> int:
    parts, by_scene, metric, scenes = scene_parts(args)
    n = len(scenes)
    refiner = load_refiner(DEFAULT_MODEL).eval()
    print(f"CPU time per query at Cambridge settings: {n} queries of {', '.join(args.scenes)}, "
          f"{FEATURES.resize} px, image scales {list(FEATURES.image_scales)}, {CAMBRIDGE.num_dbs} references, "
          f"{CAMBRIDGE.num_iters} LM iterations per level, one torch thread, model {DEFAULT_MODEL}", flush=True)
    bf16 = {True: "native", False: "emulated: the bfloat16 rows are slower here than on a CPU with AVX512-BF16",
            None: "unknown"}[native_bfloat16()]
    print(f"- this CPU: {torch.backends.cpu.get_cpu_capability()}, bfloat16 {bf16}", flush=True)
    default = next(v for v in VARIANTS if v.name == DEFAULT_VARIANT)
    _run(default, refiner, parts, {})  # untimed: the images and store blocks are read once
    variants = VARIANTS + (COMPILED if args.compile else [])
    if args.variants:
        variants = [v for v in VARIANTS + COMPILED if v.name == "today" or v.name in args.variants]
    compile_s: Dict[str, float] = {}
    rounds: Dict[str, List[Dict]] = {}
    earlier_rounds: List[Dict] = []
    for k in range(max(args.rounds, 1)):
        for v in variants:
            rounds.setdefault(v.name, []).append(_run(v, refiner, parts, compile_s))
            print(f"- {v.name}{f' (round {k + 1})' if args.rounds > 1 else ''}: "
                  f"{rounds[v.name][-1]['cpu'] / n:.3f} CPU s per query", flush=True)
        if args.earlier_code:
            earlier_rounds.append(run_earlier(args.earlier_code, args.work, args.shared, args.scenes, args.limit))
    runs = {name: dict(median_run(rs), scenes=scenes) for name, rs in rounds.items()}
    today = runs["today"]
    rows = [dict(variant=v.name, cpu_s=runs[v.name]["cpu"] / n, speedup=today["cpu"] / runs[v.name]["cpu"],
                 cpu_s_rounds=[c / n for c in runs[v.name]["cpu_rounds"]],
                 before_lm_s=runs[v.name]["before"] / n, features_s=runs[v.name]["network"] / n,
                 lm_s=runs[v.name]["lm"] / n, **_differences(runs[v.name], today, metric),
                 recalls=recalls(runs[v.name], by_scene)) for v in variants]
    header = ["variant", "CPU s/query", "vs today", "before the LM s", "features s", "LM s", "max |dc| mm (metric)",
              "max |dc| % (others)", "max dR deg", "refined by one only"] + accuracy.RECALLS
    print("\n| " + " | ".join(header) + " |\n|" + "---|" * len(header))
    for r in rows:
        cells = [r["variant"], f"{r['cpu_s']:.3f}", f"{r['speedup']:.2f}x", f"{r['before_lm_s']:.3f}",
                 f"{r['features_s']:.3f}", f"{r['lm_s']:.3f}", f"{r['max_dt_mm']:.3f}", f"{r['max_dt_pct']:.4f}",
                 f"{r['max_dR']:.4f}", str(r["unmatched"])] + [f"{x:.0f}" for x in r["recalls"]]
        print("| " + " | ".join(cells) + " |")
    for name, seconds in compile_s.items():
        print(f"- {name}: compiling took {seconds:.0f} s (one-off per process and shape family)")
    passes = search_passes(refiner, parts[0])
    print(f"- the search prior on {parts[0][0]}: {passes['runs']:.0f} LM runs of candidate poses per query (the "
          f"coarse screening of every start included), {passes['passes']:.1f} network passes per query "
          f"({len(FEATURES.image_scales)} image scales)")
    onnx = onnx_network_seconds(refiner, args.work) if args.onnx else None
    if onnx:
        print(f"- one network pass at 1024 x 672 px: today {onnx['today']:.3f} s, prepared {onnx['prepared']:.3f} s, "
              f"ONNX Runtime {onnx['onnxruntime']:.3f} s")
    earlier = _earlier(args, parts, runs, earlier_rounds, by_scene, metric) if args.earlier_code else None
    (args.work / "rows.json").write_text(json.dumps({"queries": n, "rows": rows, "search": passes,
                                                     "compile_s": compile_s, "onnx": onnx, "earlier": earlier},
                                                    indent=1))
    return 0


def median_run(rounds: List[Dict]) -> Dict:
    """A variant's run of median CPU time over its rounds (the lower middle one of an even count; every
    round gives the same poses), with every round's CPU seconds (``cpu_rounds``)."""
    return dict(_middle(rounds, "cpu"), cpu_rounds=[r["cpu"] for r in rounds])


def _middle(rounds: List[Dict], key: str) -> Dict:
    """The round of median ``key`` (the lower middle one of an even count)."""
    return sorted(rounds, key=lambda r: r[key])[(len(rounds) - 1) // 2]


def _earlier(args: argparse.Namespace, parts, runs: Dict, rounds: List[Dict], by_scene, metric) -> Dict:
    """The queries run by the code of ``--earlier-code`` (``earlier_code``) in each round, against the
    default variant: speed-ups of the median CPU times, and of each round's."""
    earlier = _middle(rounds, "cpu_s")
    keys = [(f"{name}/{q.name}", key) for name, _, queries, key in parts for q in queries]
    n = len(keys)
    # each variant's speed-up against it (today's and the default's among them)
    out = {"rev": args.earlier_code, "cpu_s": earlier["cpu_s"] / n, "cpu_s_rounds": [r["cpu_s"] / n for r in rounds],
           "speedups": {name: earlier["cpu_s"] / run["cpu"] for name, run in runs.items()},
           "speedups_per_round": {name: [e["cpu_s"] / c for e, c in zip(rounds, run["cpu_rounds"])]
                                  for name, run in runs.items()}}
    default = runs.get(DEFAULT_VARIANT)
    if default is not None:
        refined = {k: r.refined for (k, _), r in zip(keys, default["results"])}
        out.update(**pose_differences(
            {k: p["refined"] for k, p in earlier["poses"].items()}, refined,
            {k: metric[key] for k, key in keys}, {k: by_scene[key][1] for k, key in keys}))
    print(f"- the code of {args.earlier_code} (its own network, settings and verification): {out['cpu_s']:.3f} CPU s "
          f"per query (today, its emulation: {runs['today']['cpu'] / n:.3f})")
    if default is not None:
        print(f"  the default is {out['speedups'][DEFAULT_VARIANT]:.2f}x faster than it; its poses against the "
              f"default's: max |dc| {out['max_dt_mm']:.3f} mm (metric), {out['max_dt_pct']:.4f} % (others), max dR "
              f"{out['max_dR']:.4f} deg, {out['unmatched']} refined by one only")
    for name, speedup in out["speedups"].items():
        per_round = out["speedups_per_round"][name]
        print(f"  {name}: {speedup:.2f}x faster than it" + (
            f" (rounds: {', '.join(f'{x:.2f}x' for x in per_round)})" if len(per_round) > 1 else ""))
    return out
