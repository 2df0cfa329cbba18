"""A classical retrieval index from the map's own SIFT: a bag of visual words with tf-idf weights
(Sivic and Zisserman 2003, Nister and Stewenius 2006), what COLMAP's vocabulary tree ranks by.

The vocabulary is trained on the map: spherical k-means of the RootSIFT descriptors of its
observations (the keypoints that lie on map points; the store's, ``build-map --sift``, else
extracted from the map's images within ``MAX_GAP`` pixels of an observation). Each map image is a
sparse tf-idf vector (square-rooted word counts against burstiness, idf, L2-normalised), kept as an
inverted file: a query's SIFT is quantised and scored against every image in one pass over the
lists of its words. pycolmap 4.2's ``VisualIndex`` cannot return its scores to Python (its query
fills a copied list), hence this equivalent.

``index_for(reader)`` builds a map's index once per process.
"""

import logging
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

import numpy as np

from pipeline.keypoints import MAX_GAP, extract_sift, from_uint8, nearest_within

logger = logging.getLogger(__name__)


def root_sift(descriptors: np.ndarray) -> np.ndarray:
    """RootSIFT (Arandjelovic and Zisserman 2012) of L2-normalised SIFT: the Hellinger kernel as a dot product."""
    d = np.sqrt(np.maximum(descriptors, 0) / np.maximum(np.abs(descriptors).sum(1, keepdims=True), 1e-12))
    return d.astype(np.float32)


def vocabulary_size(num_descriptors: int) -> int:
    """Words for a map: about 100 descriptors per word, a power of two in [256, 8192]."""
    return int(2 ** np.clip(np.round(np.log2(max(num_descriptors, 1) / 100)), 8, 13))


def nearest_word(descriptors: np.ndarray, words: np.ndarray, chunk: int = 8192) -> np.ndarray:
    """Each descriptor's word: the centroid of largest dot product (unit vectors: the nearest)."""
    out = np.empty(len(descriptors), np.int64)
    for s in range(0, len(descriptors), chunk):
        out[s:s + chunk] = np.argmax(descriptors[s:s + chunk] @ words.T, axis=1)
    return out


def train_vocabulary(descriptors: np.ndarray, size: int, iterations: int = 10, sample: int = 100_000,
                     seed: int = 0) -> np.ndarray:
    """(size, 128) unit centroids: spherical k-means on at most ``sample`` descriptors (seeded)."""
    rng = np.random.default_rng(seed)
    x = descriptors[rng.permutation(len(descriptors))[:sample]]
    size = min(size, len(x))
    words = x[rng.choice(len(x), size, replace=False)].copy()
    for _ in range(iterations):
        assign = nearest_word(x, words)
        sums = np.zeros_like(words)
        np.add.at(sums, assign, x)
        empty = np.linalg.norm(sums, axis=1) < 1e-12
        sums[empty] = x[rng.choice(len(x), int(empty.sum()), replace=False)]  # a word without descriptors restarts
        words = sums / np.linalg.norm(sums, axis=1, keepdims=True)
    return words.astype(np.float32)


@dataclass
class BagOfWords:
    """The index: ``words`` (W, 128), ``idf`` (W,), and the inverted file: for word w, the images
    ``image[start[w]:start[w + 1]]`` with their weights ``weight[...]`` (tf-idf, each image's vector
    of unit length). ``images`` are the map's image indices that were indexed."""

    words: np.ndarray
    idf: np.ndarray
    start: np.ndarray
    image: np.ndarray
    weight: np.ndarray
    images: np.ndarray
    seconds: Dict[str, float] = field(default_factory=dict)  # what building it took: descriptors, index

    @classmethod
    def build(cls, per_image: List[Tuple[int, np.ndarray]], size: Optional[int] = None) -> "BagOfWords":
        """From (map image index, RootSIFT descriptors) per image."""
        per_image = [(i, d) for i, d in per_image if len(d)]
        if not per_image:
            raise ValueError("no SIFT descriptors on the map's observations: nothing to index.")
        everything = np.concatenate([d for _, d in per_image])
        words = train_vocabulary(everything, size or vocabulary_size(len(everything)))
        W = len(words)
        counts = [np.bincount(nearest_word(d, words), minlength=W) for _, d in per_image]
        df = np.count_nonzero(np.stack(counts), axis=0)
        idf = np.log(len(per_image) / np.maximum(df, 1)).astype(np.float32)
        rows, cols, vals = [], [], []
        for k, c in enumerate(counts):
            w = np.flatnonzero(c)
            v = np.sqrt(c[w]) * idf[w]
            norm = np.linalg.norm(v)
            keep = v > 0
            rows.append(np.full(int(keep.sum()), k))
            cols.append(w[keep])
            vals.append(v[keep] / max(norm, 1e-12))
        rows, cols, vals = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
        order = np.argsort(cols, kind="stable")
        start = np.searchsorted(cols[order], np.arange(W + 1)).astype(np.int64)
        return cls(words, idf, start, rows[order].astype(np.int32), vals[order].astype(np.float32),
                   np.array([i for i, _ in per_image], np.int64))

    def nbytes(self) -> int:
        """Bytes of the index (vocabulary, idf, inverted file)."""
        return sum(a.nbytes for a in (self.words, self.idf, self.start, self.image, self.weight, self.images))

    def scores(self, descriptors: np.ndarray) -> np.ndarray:
        """Cosine similarity of the query's tf-idf vector (RootSIFT ``descriptors``) with each indexed image."""
        out = np.zeros(len(self.images), np.float64)
        if len(descriptors) == 0:
            return out
        c = np.bincount(nearest_word(descriptors, self.words), minlength=len(self.words))
        w = np.flatnonzero(c)
        q = np.sqrt(c[w]) * self.idf[w]
        q = q / max(np.linalg.norm(q), 1e-12)
        lengths = self.start[w + 1] - self.start[w]
        at = np.repeat(self.start[w] - np.r_[0, np.cumsum(lengths)[:-1]], lengths) + np.arange(lengths.sum())
        return np.bincount(self.image[at], weights=self.weight[at] * np.repeat(q, lengths),
                           minlength=len(self.images)) if len(at) else out


def map_descriptors(reader, i: int, max_size: int) -> np.ndarray:
    """RootSIFT of map image i at its observations: the store's, else extracted from its image."""
    stored = reader.sift_descriptors(i)
    if stored is not None:
        return root_sift(from_uint8(stored[stored.any(1)]))
    from pipeline.images import read_image
    from pipeline.keypoints import MAX_FEATURES

    rgb = read_image(reader.image_path(i))
    xy, d = extract_sift(rgb, max_size, MAX_FEATURES)
    camera = reader.cameras[i]
    xy = xy * np.array([camera.width / rgb.shape[1], camera.height / rgb.shape[0]])
    obs = reader.image_xy(i)
    obs = obs[np.isfinite(obs).all(1) & (reader.image_points(i) >= 0)]
    on_points = nearest_within(xy, obs, MAX_GAP) >= 0
    return root_sift(d[on_points])


_INDEXES: "OrderedDict[Tuple[str, Tuple[str, ...], int], BagOfWords]" = OrderedDict()
_BUILDING = threading.Lock()


def _index(reader, max_size: int) -> BagOfWords:
    from pipeline.images import ImageReadError

    names = reader.names
    per_image = []
    t0 = time.perf_counter()
    for i in range(len(names)):
        if not reader.usable(i):
            continue
        try:
            per_image.append((i, map_descriptors(reader, i, max_size)))
        except ImageReadError as e:  # an image moved away: the others are indexed
            logger.warning("%s: left out of the SIFT index: %s", names[i], e)
    t1 = time.perf_counter()
    index = BagOfWords.build(per_image)
    index.seconds = {"descriptors": t1 - t0, "index": time.perf_counter() - t1}
    logger.info("SIFT index of %s: %d images, %d words, %.1f KB per image", reader.path, len(index.images),
                len(index.words), index.nbytes() / 1024 / max(len(index.images), 1))
    return index


def index_for(reader, max_size: int = 1600) -> BagOfWords:
    """The map's bag-of-words index, built on first use and kept for the process."""
    key = (str(reader.path), tuple(reader.names), max_size)
    with _BUILDING:  # threads of one worker that rank against the same map build its index once
        if key not in _INDEXES:
            _INDEXES[key] = _index(reader, max_size)
            while len(_INDEXES) > 4:
                _INDEXES.popitem(last=False)
        return _INDEXES[key]


def query_descriptors(rgb: np.ndarray, max_size: int, max_features: int) -> np.ndarray:
    """RootSIFT of a query image."""
    return root_sift(extract_sift(rgb, max_size, max_features)[1])
