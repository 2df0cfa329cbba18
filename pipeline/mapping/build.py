"""Map building stages: scene structure into the store, then features image by image.

Both stages are idempotent: structure is reused when it describes the same
scene, and feature extraction skips images already done, so an interrupted
build resumes where it stopped. A bad image is recorded as failed with its
reason; the rest of the map is built.
"""

import logging
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence

import numpy as np
import torch

from pipeline.images import read_image, resize_max, to_tensor
from pipeline.mapping.features import FeatureConfig, extract_image_features
from pipeline.models import network
from pipeline.runtime import keep_freed_memory, torch_threads
from pipeline.scene import Scene
from pipeline.store.compression import fit_pca
from pipeline.store.feature_groups import (DONE, FAILED, PENDING, FeatureWriter, finish_group, image_count,
                                           image_states)
from pipeline.store.structure import create_store

logger = logging.getLogger(__name__)
REFUSED = "refused: "  # reason prefix of images that cannot be used at all (not retried)


@dataclass
class ImageResult:
    """Outcome of one image: ``done`` (computed now), ``skipped`` (already done) or ``failed``."""

    index: int
    name: str
    status: str
    reason: str = ""


def write_structure(scene: Scene, store_path, conf: FeatureConfig, *, chunk_rows: int = 256,
                    overwrite: bool = False, source: Optional[Dict] = None, device: str = "cpu",
                    shard_rows: Optional[int] = None) -> List[int]:
    """Create the store and its feature group; record images that cannot be used as failed.

    Returns the images (store indices) whose features are still to be made (``pending_images``).
    """
    problems = scene.check()
    create_store(store_path, scene, chunk_rows=chunk_rows, overwrite=overwrite, source=source, shard_rows=shard_rows)
    net, digest = network(conf.model, device)
    writer = FeatureWriter(store_path, conf, digest, list(net.output_dims),
                           fit_pca=lambda: fit_store_pca(scene, conf, net, problems, device), scene=scene)
    index, status, reasons = writer.index, writer.status, writer.reasons  # an added session's order may differ
    for k, i in enumerate(index):
        if k in problems and status[i] != DONE:
            writer.fail(i, f"{REFUSED}{problems[k]}")
            status[i], reasons[i] = FAILED, f"{REFUSED}{problems[k]}"
            logger.warning("Image %s left out of the map: %s", scene.images[k].name, problems[k])
        elif k not in problems and status[i] == FAILED and str(reasons[i]).startswith(REFUSED):
            writer.retry(i)  # the problem is gone (e.g. the file is back)
            status[i] = PENDING
    return _pending(status, reasons)


def _pending(status: np.ndarray, reasons: np.ndarray) -> List[int]:
    """Images not done: pending, or failed for a reason that may pass (not refused)."""
    return [i for i, (s, r) in enumerate(zip(status, reasons)) if s != DONE and not str(r).startswith(REFUSED)]


def fit_store_pca(scene: Scene, conf: FeatureConfig, net, problems: Dict[int, str], device: str = "cpu",
                  num_images: int = 8) -> Dict:
    """PCA bases (``FeatureConfig.pca``) per image scale and level, fitted on the dense feature maps
    (every pixel) of ``num_images`` of the scene's usable images, evenly spread, at the store's
    resolutions (one torch thread: the same images give the same bases)."""
    usable = [i for i in range(len(scene.images)) if i not in problems]
    chosen = usable[::max(1, len(usable) // num_images)][:num_images]
    dims = list(net.output_dims)
    reduced = [level for level, d in enumerate(dims) if conf.pca and d > conf.pca]
    samples: Dict = {}
    with torch_threads(1), torch.inference_mode():
        for i in chosen:
            try:
                rgb = read_image(scene.images[i].path)
            except (OSError, ValueError) as e:  # the build records it; the PCA uses the others
                logger.warning("PCA sample %s left out: %s", scene.images[i].name, e)
                continue
            for k, image_scale in enumerate(conf.image_scales):
                resized, _ = resize_max(rgb, conf.resize // image_scale)
                pred = net(to_tensor(resized)[None].to(device))
                for level in reduced:
                    fmap = pred["features"][level][0]
                    samples.setdefault((k, level), []).append(fmap.reshape(len(fmap), -1).T.cpu().numpy())
    bases = {}
    for k in range(len(conf.image_scales)):
        for level in reduced:
            x = np.concatenate(samples.get((k, level), [np.zeros((0, dims[level]), np.float32)]))
            if not len(x):
                raise ValueError(f"No image of the map could be read to fit the PCA of its features (image scale "
                                 f"{k}, level {level}; {len(chosen)} tried): fix the images, or store every channel "
                                 "with --pca 0.")
            if len(x) < conf.pca:  # fit_pca completes the basis: the samples are kept exactly
                logger.warning("The PCA of level %d (image scale %d) has %d feature samples in the %d images "
                               "sampled, fewer than its %d components: they are kept exactly, the other "
                               "directions are fixed ones (a small map at --resize %d; --pca 0 stores every "
                               "channel).", level, k, len(x), len(chosen), conf.pca, conf.resize)
            bases[(k, level)] = fit_pca(x, conf.pca)
    logger.info("Fitted the PCA of the features (%d components) on %d images.", conf.pca, len(chosen))
    return bases


def extract_features(store_path, conf: FeatureConfig, indices: Sequence[int], device: str = "cpu", *,
                     overwrite: bool = False) -> List[ImageResult]:
    """Extract and write the features of images ``indices``; one task of the map-building graph.

    Runs with one torch thread (``torch_threads``): stores are then bitwise
    identical whatever executor built them.
    """
    keep_freed_memory()
    with torch_threads(1), torch.inference_mode():
        return _extract_features(store_path, conf, indices, device, overwrite)


def _extract_features(store_path, conf, indices, device, overwrite) -> List[ImageResult]:
    net, digest = network(conf.model, device)
    writer = FeatureWriter(store_path, conf, digest, list(net.output_dims))  # refuses another model
    images, xyz = writer.contents()
    results = []
    for i in indices:
        image = images[i]
        status, reason, observed = writer.state(i)
        if status == DONE and not overwrite:
            results.append(ImageResult(i, image.name, "skipped"))
            continue
        if status == FAILED and reason.startswith(REFUSED):
            results.append(ImageResult(i, image.name, "failed", reason))
            continue
        try:
            feats = extract_image_features(net, conf, image, xyz[observed], device=device)
        except (OSError, ValueError, RuntimeError) as e:  # per-image failure, recorded with its reason
            reason = f"{type(e).__name__}: {e}"
            writer.fail(i, reason)
            logger.warning("Image %s failed: %s", image.name, reason)
            results.append(ImageResult(i, image.name, "failed", reason))
            continue
        writer.write(i, feats)
        results.append(ImageResult(i, image.name, "done"))
    return results


def pending_images(store_path, conf: FeatureConfig) -> List[int]:
    """Images whose features are not done (pending, or failed for a reason that may pass)."""
    states = image_states(store_path, conf)
    return list(range(image_count(store_path))) if states is None else _pending(*states)


def finish_build(store_path, conf: FeatureConfig) -> None:
    """After a build: consolidate the feature group's per-image arrays for fast opening
    (``pipeline.store.layout.consolidate``), unless they already are."""
    finish_group(store_path, conf)


def build_map(scene: Scene, store_path, conf: FeatureConfig, **kwargs) -> List[ImageResult]:
    """Synchronous map build: structure, then every pending image in order."""
    pending = write_structure(scene, store_path, conf, **kwargs)
    results = extract_features(store_path, conf, pending, device=kwargs.get("device", "cpu"))
    finish_build(store_path, conf)
    return results
