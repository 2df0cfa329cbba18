"""``pixloc train-whitening``: the learned whitening of the ``gem-lw`` global descriptor, in closed form
from posed map images (Mikolajczyk and Matas 2007, as Radenovic et al. 2018 learn it on GeM).

Every usable image of the given map stores is described as the network sees it (GeM of its coarsest
features, L2-normalised, as ``gem``) and as ``--relit`` copies relit to night by the training's
photometric change (``night_change``, seeded by image), the vectors cached in ``--work``. Matching
pairs: an image and its relit copies, and two images of one map that share at least ``--min-share``
of the smaller one's map points (co-visible); non-matching pairs: images of one map sharing less than
a tenth of that, and images of different maps. The whitening is C_S^-1/2 of the matching pairs'
difference covariance (shrunk by ``--shrink`` towards its mean variance), then rotated to the
principal axes of the non-matching pairs' differences: descriptor = normalise(P (gem - mean)).

It writes ``--out`` (npz: mean, projection, and which maps trained it), which ``gem-lw`` reads
(``pipeline.descriptors``; the shipped one is pixloc/nets/weights/pixloc-lite0.gem-lw.npz).
"""

import argparse
import json
import zlib
from pathlib import Path
from typing import Dict, List, Tuple

import numpy as np


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("stores", nargs="+", type=Path, help="map stores of the training scenes (posed images, points)")
    p.add_argument("--out", type=Path, required=True, help="the whitening file to write (.npz)")
    p.add_argument("--work", type=Path, default=Path("outputs/whitening"), help="cached descriptors")
    p.add_argument("--relit", type=int, default=2, help="relit copies per image")
    p.add_argument("--min-share", type=float, default=0.3,
                   help="co-visible pairs share at least this fraction of the smaller image's points")
    p.add_argument("--shrink", type=float, default=0.1, help="shrinkage of the matching pairs' covariance")


def image_descriptors(store: Path, work: Path, relit: int) -> Tuple[List[str], np.ndarray]:
    """(names, (n, 1 + relit, C)) GeM descriptors of a store's usable images, cached per store."""
    import torch

    from pipeline.data.photo_pairs import night_change
    from pipeline.descriptors import GeM, global_descriptor
    from pipeline.images import read_image
    from pipeline.localization.refine import Localizer, LocalizerConfig
    from pipeline.models import localization_model
    from pipeline.store.info import feature_config
    from pipeline.store.reader import MapReader

    cache = work / f"{store.name}.relit{relit}.npz"
    if cache.exists():
        z = np.load(cache, allow_pickle=False)
        return [str(n) for n in z["names"]], z["x"]
    conf = feature_config(store)
    refiner, digest = localization_model(conf.model, "cpu")
    reader = MapReader(store, conf, digest)
    localizer = Localizer(refiner.extractor, refiner.solvers, reader, LocalizerConfig(), "cpu")
    names, out = [], []
    with torch.no_grad():
        for i, name in enumerate(reader.names):
            if not reader.usable(i):
                continue
            rgb = read_image(reader.image_path(i))
            rng = np.random.default_rng(zlib.crc32(name.encode()))
            variants = [rgb] + [(night_change(rgb.astype(np.float32) / 255, rng) * 255).round().astype(np.uint8)
                                for _ in range(relit)]
            k_last = len(conf.image_scales) - 1
            out.append([global_descriptor(localizer.predict(v, k_last)[0]["features"][-1][0], GeM.name).numpy()
                        for v in variants])
            names.append(name)
    work.mkdir(parents=True, exist_ok=True)
    x = np.asarray(out, np.float32)
    np.savez(cache, names=np.array(names), x=x)
    return names, x


def shared_points(store: Path, names: List[str]) -> np.ndarray:
    """(n, n): the share of the smaller image's map points that two images both observe."""
    from pipeline.store.info import feature_config
    from pipeline.store.reader import MapReader

    reader = MapReader(store, feature_config(store))
    points = [set(reader.image_points(reader.index[n]).tolist()) - {-1} for n in names]
    n = len(names)
    share = np.zeros((n, n))
    for a in range(n):
        for b in range(a + 1, n):
            share[a, b] = share[b, a] = len(points[a] & points[b]) / max(min(len(points[a]), len(points[b])), 1)
    return share


def learn(per_map: List[Tuple[np.ndarray, np.ndarray]], min_share: float, shrink: float) -> Dict[str, np.ndarray]:
    """The whitening from (descriptors (n, V, C), shared points (n, n)) per map (see the module)."""
    everything = np.concatenate([x.reshape(-1, x.shape[-1]) for x, _ in per_map])
    mean = everything.mean(0)
    same, other = [], []
    offsets = np.cumsum([0] + [x.shape[0] * x.shape[1] for x, _ in per_map])
    owner = np.concatenate([np.full(x.shape[0] * x.shape[1], k) for k, (x, _) in enumerate(per_map)])
    for k, (x, share) in enumerate(per_map):
        n, V, _ = x.shape
        for a in range(n):
            for u in range(V):
                for v in range(u + 1, V):
                    same.append(x[a, u] - x[a, v])  # an image and its relit copies
            for b in range(a + 1, n):
                for u in range(V):
                    if share[a, b] >= min_share:
                        same.append(x[a, u] - x[b, u])
                    elif share[a, b] < min_share / 10:
                        other.append(x[a, u] - x[b, u])
    rng = np.random.default_rng(0)  # pairs of different maps, as many as the non-matching ones of one map
    i, j = rng.integers(len(everything), size=(2, 4 * max(len(other), len(everything))))
    keep = owner[i] != owner[j]
    other += list(everything[i[keep]] - everything[j[keep]])
    same, other = np.asarray(same), np.asarray(other)
    C_s = same.T @ same / len(same)
    C_s = (1 - shrink) * C_s + shrink * np.trace(C_s) / len(C_s) * np.eye(len(C_s))
    w, V = np.linalg.eigh(C_s)
    whiten = V @ np.diag(1 / np.sqrt(np.maximum(w, 1e-12))) @ V.T
    d = other @ whiten.T
    w_d, V_d = np.linalg.eigh(d.T @ d / len(d))
    projection = V_d[:, np.argsort(-w_d)].T @ whiten
    return {"mean": mean.astype(np.float32), "projection": projection.astype(np.float32),
            "pairs": np.array([len(same), len(other)]), "offsets": offsets}


def main(args: argparse.Namespace) -> int:
    per_map = []
    for store in args.stores:
        names, x = image_descriptors(store, args.work, args.relit)
        per_map.append((x, shared_points(store, names)))
        print(f"{store.name}: {len(names)} images", flush=True)
    found = learn(per_map, args.min_share, args.shrink)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    trained_on = json.dumps({"stores": [s.name for s in args.stores], "relit": args.relit,
                             "min_share": args.min_share, "shrink": args.shrink,
                             "pairs": {"matching": int(found["pairs"][0]), "non_matching": int(found["pairs"][1])}})
    np.savez(args.out, mean=found["mean"], projection=found["projection"], trained_on=np.array(trained_on))
    print(f"wrote {args.out}: {trained_on}")
    return 0
