"""Compression of the stored reference features: int8 codes with a scale per row and level, and
principal components (PCA) per level. Pure numpy; ``pipeline.store.layout`` writes them, ``MapReader``
reads them back."""

from typing import List, Tuple

import numpy as np


def quantize_int8(features: np.ndarray, dims: List[int]) -> Tuple[np.ndarray, np.ndarray]:
    """(N, sum(dims)) float -> int8 codes and (N, L) float16 scales, one per row and level:
    x = code * scale, |error| <= scale / 2 = max|x| / 254 of the row's level."""
    edges = np.cumsum([0] + list(dims))
    codes = np.zeros(features.shape, np.int8)
    scales = np.zeros((len(features), len(dims)), np.float16)
    for level in range(len(dims)):
        x = features[:, edges[level]:edges[level + 1]].astype(np.float32)
        s = (np.abs(x).max(1) / 127).astype(np.float16)  # rounded first, so codes use the stored scale
        safe = np.where(s > 0, s.astype(np.float32), 1)[:, None]
        codes[:, edges[level]:edges[level + 1]] = np.clip(np.rint(x / safe), -127, 127)
        scales[:, level] = s
    return codes, scales


def dequantize_int8(codes: np.ndarray, scales: np.ndarray, dims: List[int]) -> List[np.ndarray]:
    """Per level, float32 features from int8 codes and per-row scales."""
    edges = np.cumsum([0] + list(dims))
    return [codes[:, edges[i]:edges[i + 1]].astype(np.float32) * scales[:, i:i + 1].astype(np.float32)
            for i in range(len(dims))]


def fit_pca(samples: np.ndarray, components: int, max_rows: int = 50_000, seed: int = 0
            ) -> Tuple[np.ndarray, np.ndarray]:
    """Mean (C,) and the ``components`` leading principal directions (C, D), orthonormal columns, of
    the rows of ``samples`` (N, C) (a seeded subset of at most ``max_rows``), float32. Fewer samples
    than components (a small map at a low resolution: every pixel of its coarsest maps) span fewer
    directions: those come first, and a fixed orthonormal completion fills the rest, so that the
    samples are kept exactly and the stored width is the configured one."""
    x = np.asarray(samples, np.float64)
    if not len(x) or components > x.shape[1]:
        raise ValueError(f"A PCA of {components} components of {x.shape[1]} channels cannot be fitted on "
                         f"{len(x)} samples.")
    if len(x) > max_rows:
        x = x[np.sort(np.random.default_rng(seed).choice(len(x), max_rows, replace=False))]
    mean = x.mean(0)
    _, sv, vt = np.linalg.svd(x - mean, full_matrices=False)
    directions = vt[:components].T
    if directions.shape[1] < components:  # complete with the axes, orthogonalised (QR keeps the first columns' span)
        q, _ = np.linalg.qr(np.concatenate([directions, np.eye(x.shape[1])], 1))
        directions = q[:, :components] * np.sign(np.sum(q[:, :directions.shape[1]] * directions, 0).tolist()
                                                 + [1.0] * (components - directions.shape[1]))
    return mean.astype(np.float32), np.ascontiguousarray(directions).astype(np.float32)


def project(features: np.ndarray, basis: Tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """(N, C) features -> (N, D) float32 components of ``basis`` (mean, directions). Summed in
    float64, so that the result does not depend on how many threads BLAS splits the product into
    (a sync run and a Dask worker's must store and read the same values)."""
    mean, directions = basis
    return ((np.asarray(features, np.float64) - mean) @ directions.astype(np.float64)).astype(np.float32)


def reconstruct(components: np.ndarray, basis: Tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """(N, D) components -> (N, C) float32 features (summed in float64, as ``project``)."""
    mean, directions = basis
    return (np.asarray(components, np.float64) @ directions.T.astype(np.float64) + mean).astype(np.float32)
