"""SIFT keypoints and descriptors (pycolmap), and where they meet a map's observations: the map
build stores a descriptor per observation (``FeatureConfig.sift``) and the ``sift`` prior matches
a query's descriptors to them (``pipeline.localization.sift``).

Stored descriptors are uint8, as COLMAP keeps them: the L2-normalised descriptor times 512,
clipped to 255; a row of zeros is an observation without a keypoint near it."""

import warnings
from typing import Tuple

import numpy as np

DESCRIPTOR_DIM = 128
MAX_FEATURES = 4096  # per image
MAX_GAP = 2.0  # pixels between a keypoint and the observation it stands for


def extract_sift(rgb: np.ndarray, max_size: int, max_features: int) -> Tuple[np.ndarray, np.ndarray]:
    """Keypoints (N, 2) in COLMAP pixel coordinates of ``rgb`` and L2-normalised descriptors (N, 128),
    extracted at a longer side of at most ``max_size`` pixels."""
    import cv2
    import pycolmap

    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    scale = min(1.0, max_size / max(gray.shape))
    if scale < 1:
        gray = cv2.resize(gray, (round(gray.shape[1] * scale), round(gray.shape[0] * scale)),
                          interpolation=cv2.INTER_AREA)
    options = pycolmap.FeatureExtractionOptions()
    options.sift.max_num_features = max_features
    options.num_threads = 1
    with warnings.catch_warnings():  # pycolmap 4 deprecates Sift for FeatureExtractor, whose keypoints are
        warnings.simplefilter("ignore", DeprecationWarning)  # Python objects, one per keypoint: kept for arrays
        keypoints, descriptors = pycolmap.Sift(options, pycolmap.Device.cpu).extract(np.ascontiguousarray(gray))
    xy = np.asarray(keypoints[:, :2], np.float64) / scale
    d = np.asarray(descriptors, np.float32)
    return xy, d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


def nearest_within(query: np.ndarray, points: np.ndarray, gap: float) -> np.ndarray:
    """For each query position, the index of the nearest of ``points`` within ``gap`` pixels, else -1."""
    out = np.full(len(query), -1, np.int64)
    if len(points) == 0 or len(query) == 0:
        return out
    for start in range(0, len(query), 1024):
        q = query[start:start + 1024]
        d = ((q[:, None, :] - points[None, :, :]) ** 2).sum(-1)
        j = np.argmin(d, axis=1)
        ok = d[np.arange(len(q)), j] <= gap ** 2
        out[start:start + len(q)][ok] = j[ok]
    return out


def to_uint8(descriptors: np.ndarray) -> np.ndarray:
    """L2-normalised descriptors as stored: x 512, rounded, clipped to [0, 255] (COLMAP's uint8)."""
    return np.clip(np.round(np.asarray(descriptors, np.float32) * 512), 0, 255).astype(np.uint8)


def from_uint8(codes: np.ndarray) -> np.ndarray:
    """Stored descriptors back as L2-normalised float32 (zero rows stay zero)."""
    d = np.asarray(codes, np.float32)
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


def observation_descriptors(xy: np.ndarray, descriptors: np.ndarray, observations: np.ndarray,
                            gap: float) -> np.ndarray:
    """(K, 128) uint8: for each observation (K, 2; COLMAP pixels), the descriptor of the keypoint
    nearest to it within ``gap`` pixels (one keypoint serves one observation, the nearest), else
    zeros."""
    out = np.zeros((len(observations), DESCRIPTOR_DIM), np.uint8)
    finite = np.flatnonzero(np.isfinite(observations).all(1))
    nearest = nearest_within(observations[finite], xy, gap)
    hit = nearest >= 0
    rows, keys = finite[hit], nearest[hit]
    if len(rows):
        gaps = np.linalg.norm(observations[rows] - xy[keys], axis=1)
        order = np.lexsort((gaps, keys))  # per keypoint, its nearest observation first
        first = order[np.r_[True, keys[order][1:] != keys[order][:-1]]]
        out[rows[first]] = to_uint8(descriptors[keys[first]])
    return out
