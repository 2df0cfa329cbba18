"""Which map images a query is localized against: its references, ranked.

The registry ``RETRIEVERS`` (the job's ``retrieval`` and the command line's choices come from
it): an entry is its settings dataclass (``k`` and ``same_tag`` shared by all, in
``RetrievalSettings``), ``rank(reader, query, describe, candidates) -> Retrieved``:

- ``global``: the top ``k`` by cosine similarity of the store's global descriptors with the
  query's (``describe()`` runs the network on the query only when this method asks for it);
- ``pairs``: a ranked pairs file (hloc's ``pairs-query-*.txt``: ``query reference`` per line);
- ``hloc``: global descriptors of queries and references from an hloc HDF5 file (NetVLAD ...),
  as official PixLoc reads them.

``retrieve`` applies what every method shares: references found by a run's retrieval stage
(``query.retrieved``) are used as they are, and ``same_tag`` restricts the candidates to the
map images that share that tag with the query (RobotCar practice: ``camera``).

An entry's class attributes: ``help``, ``flags`` (its own options; giving one chooses the method),
``needs_image`` (it runs the network on the query: a separate retrieval stage costs one more
network pass per query), ``inputs`` (its fields that name input files). A new method is one class
here.
"""

import functools
import logging
from dataclasses import dataclass
from typing import Callable, ClassVar, Dict, List, Optional, Tuple

import numpy as np

from pipeline.store.reader import MapReader, by_name
from pipeline.queries import QueryRecord
from pipeline.registry import Registry, check_inputs
from pipeline.settings import Flag
from pipeline.textfiles import InputError, poses_file, read_pairs

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class RetrievalSettings:
    """What every retrieval method shares: k: references retrieved; same_tag: restrict references
    to those sharing this tag with the query. Each method (``RETRIEVERS``) adds its own."""

    k: int = 10
    same_tag: Optional[str] = None
    name: ClassVar[str]
    help: ClassVar[str] = ""
    flags: ClassVar[Dict[str, Flag]] = {}
    needs_image: ClassVar[bool] = False
    inputs: ClassVar[Tuple[str, ...]] = ()

    @property
    def method(self) -> str:
        return self.name

    def validate(self) -> None:
        if self.k < 1:
            raise ValueError("retrieval k must be at least 1.")
        check_inputs(self, f"Retrieval {self.name}")

    def check(self, map_names: List[str]) -> None:
        """Checks against the map, once before any query (an input that matches none of its images)."""

    def rank(self, reader: MapReader, query: QueryRecord, describe: Callable[[], np.ndarray],
             candidates: Optional[List[int]]) -> "Retrieved":
        raise NotImplementedError


RETRIEVERS = Registry("retrieval method", tag="method")


@dataclass
class Retrieved:
    """A query's references (map image indices, best first) and their similarities (None where the
    method has none, e.g. a pairs file)."""

    dbs: List[int]
    similarity: Optional[np.ndarray] = None


@functools.lru_cache(maxsize=4)
def pairs_file(path: str) -> Dict[str, List[str]]:
    """A ranked pairs file, read once per process (``pipeline.textfiles.read_pairs``)."""
    return read_pairs(path)


@functools.lru_cache(maxsize=2)
def hloc_descriptors(path: str) -> Dict[str, np.ndarray]:
    """``name -> global_descriptor`` (L2-normalised) of an hloc global-features HDF5 file."""
    import h5py

    out = {}
    try:
        with h5py.File(path, "r") as f:
            def visit(name, obj):
                if isinstance(obj, h5py.Dataset) and name.endswith("/global_descriptor"):
                    d = np.asarray(obj, np.float32).reshape(-1)
                    out[name[: -len("/global_descriptor")]] = d / max(np.linalg.norm(d), 1e-12)
            f.visititems(visit)
    except (OSError, ValueError, KeyError, TypeError) as e:  # not HDF5, truncated, a damaged dataset
        raise InputError(f"{path}: hloc global descriptors cannot be read ({type(e).__name__}: "
                         f"{str(e).splitlines()[0][:160]}): not an HDF5 file of hloc's, or damaged") from None
    dims = {len(d) for d in out.values()}
    if not out or len(dims) > 1 or not all(np.isfinite(d).all() for d in out.values()):
        what = ("holds no NAME/global_descriptor dataset" if not out else
                f"holds descriptors of {len(dims)} sizes ({', '.join(map(str, sorted(dims)))})" if len(dims) > 1
                else "holds descriptors that are not finite")
        raise InputError(f"{path}: hloc global descriptors: the file {what}.")
    return out


def check_descriptors(path: str, map_names: List[str]) -> None:
    """Read an hloc descriptors file once, before any query, and refuse one that holds none of the
    map's images (InputError naming it): every query would fail, each with the same message."""
    descriptors = hloc_descriptors(path)
    if not any(n in descriptors for n in map_names):
        raise InputError(f"{path}: hloc global descriptors: none of its {len(descriptors)} images is a map image "
                         f"(e.g. {', '.join(sorted(descriptors)[:3])}; the map's: {', '.join(map_names[:3])}).")


def global_ranking(reader: MapReader, descriptor: np.ndarray, k: int,
                   candidates: Optional[List[int]] = None) -> List[int]:
    """Top-k usable reference images by cosine similarity of global descriptors."""
    ids = np.array([i for i in (candidates if candidates is not None else range(len(reader.names)))
                    if reader.usable(i)])
    if len(ids) == 0:
        return []
    sim = reader.global_descriptors[ids] @ descriptor
    return [int(i) for i in ids[np.argsort(-sim, kind="stable")[:k]]]


@RETRIEVERS.register("global")
@dataclass(frozen=True)
class GlobalDescriptors(RetrievalSettings):
    help: ClassVar[str] = "the store's global descriptors (cosine similarity with the query's)"
    needs_image: ClassVar[bool] = True

    def rank(self, reader, query, describe, candidates) -> Retrieved:
        descriptor = describe()
        dbs = global_ranking(reader, descriptor, self.k, candidates)
        return Retrieved(dbs, reader.global_descriptors[dbs] @ descriptor)


@RETRIEVERS.register("pairs")
@dataclass(frozen=True)
class PairsFile(RetrievalSettings):
    """pairs: a ranked pairs file (hloc's ``pairs-query-*.txt``)."""

    pairs: Optional[str] = None
    help: ClassVar[str] = "a ranked pairs file (--pairs)"
    flags: ClassVar[Dict[str, Flag]] = {
        "--pairs": Flag("pairs", "retrieval pairs file (default: global descriptors)", file=True)}
    inputs: ClassVar[Tuple[str, ...]] = ("pairs",)

    def validate(self) -> None:
        super().validate()
        pairs_file(self.pairs)  # read in full now: a bad line is one clear error (file:line)

    def rank(self, reader, query, describe, candidates) -> Retrieved:
        dbs, missing = by_name(reader, pairs_file(self.pairs).get(query.name, []))
        if missing:
            logger.warning("%s: %d retrieved references are not in the map: %s", query.name, len(missing),
                           missing[:3])
        return Retrieved([i for i in dbs if reader.usable(i) and (candidates is None or i in candidates)][:self.k])


@RETRIEVERS.register("hloc")
@dataclass(frozen=True)
class HlocDescriptors(RetrievalSettings):
    """descriptors: an hloc global-features HDF5 file (NetVLAD ...), as official PixLoc reads them."""

    descriptors: Optional[str] = None
    help: ClassVar[str] = "global descriptors of an hloc HDF5 file (--descriptors)"
    flags: ClassVar[Dict[str, Flag]] = {
        "--descriptors": Flag("descriptors", "hloc HDF5 global descriptors for retrieval (e.g. NetVLAD)", file=True)}
    inputs: ClassVar[Tuple[str, ...]] = ("descriptors",)

    def check(self, map_names: List[str]) -> None:
        """Read the file once, before any query (``check_descriptors``)."""
        check_descriptors(self.descriptors, map_names)

    def rank(self, reader, query, describe, candidates) -> Retrieved:
        descriptors = hloc_descriptors(self.descriptors)
        if query.name not in descriptors:
            return Retrieved([])
        ids = [i for i in range(len(reader.names)) if reader.usable(i) and reader.names[i] in descriptors
               and (candidates is None or i in candidates)]
        sim = np.array([descriptors[reader.names[i]] @ descriptors[query.name] for i in ids])
        order = np.argsort(-sim, kind="stable")[:self.k]
        return Retrieved([ids[j] for j in order], sim[order])


def retrieve(conf: RetrievalSettings, reader: MapReader, query: QueryRecord,
             describe: Callable[[], np.ndarray]) -> Retrieved:
    """The query's usable references, best first (see the module docstring)."""
    if query.retrieved is not None:  # found by a run's retrieval stage (``shard.retrieve_queries``)
        dbs, _ = by_name(reader, query.retrieved["dbs"])
        sim = query.retrieved.get("similarity")
        keep = [j for j, i in enumerate(dbs) if reader.usable(i)]
        return Retrieved([dbs[j] for j in keep], None if sim is None else np.asarray(sim, np.float64)[keep])
    candidates = None
    if conf.same_tag:
        value = query.tags.get(conf.same_tag)
        candidates = [i for i, t in enumerate(reader.tags) if t.get(conf.same_tag) == value]
    return conf.rank(reader, query, describe, candidates)


@RETRIEVERS.register("covisible")
@dataclass(frozen=True)
class Covisible(RetrievalSettings):
    """poses: a poses file with a prior pose per query (``name qw qx qy qz tx ty tz``, cam_from_world):
    the references are the map images that observe the most map points inside the query's view at
    that pose (in front of it, projecting into its image; lens distortion left out), most first.
    Reads every usable map image's points once per process (``MapReader.image_points``)."""

    poses: Optional[str] = None
    help: ClassVar[str] = "the map images that see the most points in the view of a prior pose (--covisible-poses)"
    flags: ClassVar[Dict[str, Flag]] = {
        "--covisible-poses": Flag("poses", "covisible retrieval: a poses file with a prior pose per query",
                                  file=True)}
    inputs: ClassVar[Tuple[str, ...]] = ("poses",)

    def validate(self) -> None:
        super().validate()
        poses_file(self.poses)  # read in full now: a bad line is one clear error (file:line)

    def rank(self, reader, query, describe, candidates) -> Retrieved:
        T = poses_file(self.poses).find(query.name)
        if T is None:
            return Retrieved([])
        cam = (reader.xyz @ np.asarray(T)[:, :3].T) + np.asarray(T)[:, 3]
        f, (cx, cy) = query.camera.focals(), query.camera.principal_point()
        fx, fy = f[0], f[-1]
        z = np.maximum(cam[:, 2], 1e-9)
        u, v = fx * cam[:, 0] / z + cx, fy * cam[:, 1] / z + cy
        seen = (cam[:, 2] > 0) & (u >= 0) & (u < query.camera.width) & (v >= 0) & (v < query.camera.height)
        ids = [i for i in (candidates if candidates is not None else range(len(reader.names))) if reader.usable(i)]
        counts = np.array([np.count_nonzero(seen[reader.image_points(i)]) for i in ids], dtype=np.float64)
        order = [j for j in np.argsort(-counts, kind="stable") if counts[j] > 0][:self.k]
        return Retrieved([ids[j] for j in order], counts[order] / max(counts.max(initial=0.0), 1.0))


@RETRIEVERS.register("bow")
@dataclass(frozen=True)
class SiftWords(RetrievalSettings):
    """A bag of visual words of the map's SIFT (``pipeline.localization.bow``): the query's SIFT at
    ``sift_size`` px against a tf-idf inverted file, its vocabulary trained on the map's own descriptors
    (the store's where built with ``--sift``, else extracted from the map's images when first needed)."""

    sift_size: int = 1024
    help: ClassVar[str] = "a bag of visual words of the map's SIFT (tf-idf, a vocabulary trained on the map)"

    def rank(self, reader, query, describe, candidates) -> Retrieved:
        return top_k(reader, words_scores(reader, query, self.sift_size), self.k, candidates)


@RETRIEVERS.register("fusion")
@dataclass(frozen=True)
class Fusion(RetrievalSettings):
    """Reciprocal rank fusion (Cormack et al. 2009) of ``global`` and ``bow``: each reference scores
    sum 1 / (``rrf_k`` + its rank) over the two rankings of every map image."""

    sift_size: int = 1024
    rrf_k: int = 10
    help: ClassVar[str] = "global and bow rankings fused by their reciprocal ranks"
    needs_image: ClassVar[bool] = True

    def rank(self, reader, query, describe, candidates) -> Retrieved:
        fused = np.zeros(len(reader.names))
        for scores in (words_scores(reader, query, self.sift_size), reader.global_descriptors @ describe()):
            rank = np.empty(len(scores), np.int64)
            rank[np.argsort(-scores, kind="stable")] = np.arange(len(scores))
            fused += 1.0 / (self.rrf_k + 1 + rank)
        return top_k(reader, fused, self.k, candidates)


def words_scores(reader: MapReader, query: QueryRecord, sift_size: int) -> np.ndarray:
    """Per map image, the bag-of-words similarity with the query (0 for images not indexed)."""
    from pipeline.images import read_image
    from pipeline.keypoints import MAX_FEATURES
    from pipeline.localization.bow import index_for, query_descriptors

    index = index_for(reader)
    out = np.zeros(len(reader.names))
    out[index.images] = index.scores(query_descriptors(read_image(query.path), sift_size, MAX_FEATURES))
    return out


def top_k(reader: MapReader, scores: np.ndarray, k: int, candidates: Optional[List[int]]) -> Retrieved:
    """The ``k`` usable candidates of highest score, with their scores."""
    ids = np.array([i for i in (candidates if candidates is not None else range(len(reader.names)))
                    if reader.usable(i)], np.int64)
    if len(ids) == 0:
        return Retrieved([])
    order = ids[np.argsort(-scores[ids], kind="stable")[:k]]
    return Retrieved([int(i) for i in order], scores[order])
