"""The data sources of ``pixloc train`` and ``pixloc evaluate-model``: a config's entries (synthetic
scenes, photos for self-supervised pairs, official MegaDepth and CMU layouts, the map sources of
``pixloc build-map``) as ``Source`` objects whose ``dataset`` draws training pairs."""

import logging
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Dict, List, Optional, Tuple

from pipeline.mapping.readers.pixloc_training import read_cmu_slice, read_megadepth
from pipeline.scene import CameraRecord, Scene
from pipeline.data.photo_pairs import PhotoPairs
from pipeline.data.training_data import PairConfig, PairDataset, synthetic_scene

from pipeline.mapping.readers.sources import MapSource, load_scene
from pipeline.runtime import shared_folder

logger = logging.getLogger(__name__)
SYNTHETIC = "synthetic"  # the kind of the training source generated here (the others are map sources)


def default_data_root() -> Path:
    return shared_folder() / "data"


@dataclass
class Source:
    """A training or evaluation source: its Scene (or, for self-supervised pairs, its photos),
    sampling weight, and optionally its own pairs (official MegaDepth/CMU overlaps) and
    initial-pose range (CMU: the reference pose)."""

    name: str
    scene: Optional[Scene]
    weight: float = 1.0
    pairs: Optional[List[Tuple[int, int]]] = None
    init_range: Optional[Tuple[float, float]] = None
    photos: Tuple[Path, ...] = ()

    def dataset(self, conf: PairConfig):
        """Its pairs: a ``PairDataset``, or ``PhotoPairs`` of its photos."""
        if self.init_range is not None:
            conf = replace(conf, init_range=tuple(self.init_range))
        if self.photos:
            return PhotoPairs(self.photos, conf)
        return PairDataset([(self.name, self.scene)], conf, {self.name: self.pairs} if self.pairs else None)


def photo_files(data_root: Path, patterns: List[str], exclude: List[str] = ()) -> List[Path]:
    """The files matching ``patterns`` (globs relative to ``data_root``) that match none of
    ``exclude``, in name order; image files only."""
    found = {p for pattern in patterns for p in data_root.glob(pattern)
             if p.suffix.lower() in (".jpg", ".jpeg", ".png")}
    dropped = {p for pattern in exclude for p in data_root.glob(pattern)}
    return sorted(found - dropped)


def load_sources(entries: List[Dict], data_root: Path, work_dir: Path, camera: CameraRecord
                 ) -> Tuple[List[Source], List[str]]:
    """The sources of a config's entries; sources whose data is absent are skipped with a
    warning and their names returned second.

    Kinds: ``synthetic`` (seed, optional textures), ``photos`` (self-supervised pairs of every
    photo matching the globs ``paths``, less those matching ``exclude``: ``PhotoPairs``),
    ``megadepth`` (scene), ``cmu`` (slice), and the map sources of ``pixloc build-map`` (colmap,
    sfm, the posed formats, 7scenes, posetxt). Keys ``weight`` and ``init_range`` apply to any kind."""
    sources, skipped = [], []
    for entry in entries:
        entry = dict(entry)
        kind, weight = entry.pop("kind"), float(entry.pop("weight", 1.0))
        init_range = entry.pop("init_range", None)
        pairs = None
        if kind == SYNTHETIC:
            seed = int(entry.pop("seed"))
            textures = [data_root / t for t in entry.pop("textures", [])]
            name = f"synthetic-{seed}" + ("-photos" if textures else "")
            missing = [str(t) for t in textures if not t.is_file()]
            if missing:
                logger.warning("Textures of %s are missing (%s): skipped.", name, ", ".join(missing))
                skipped.append(name)
                continue
            scene = synthetic_scene(work_dir / name, seed, camera, textures=textures)
        elif kind == "photos":
            patterns = list(entry.pop("paths"))
            name = entry.pop("name", "photos")
            photos = photo_files(data_root, patterns, entry.pop("exclude", []))
            if not photos:
                logger.warning("Training source %s matches no photo (%s): skipped.", name, ", ".join(patterns))
                skipped.append(name)
                continue
            logger.info("Training source %s: %d photos, self-supervised pairs.", name, len(photos))
            sources.append(Source(name, None, weight, None, tuple(init_range) if init_range else None,
                                  tuple(photos)))
            continue
        else:
            path = data_root / entry.pop("path")
            name = str(path.relative_to(data_root))
            if not path.exists():
                logger.warning("Training source %s is missing (%s): skipped.", name, path)
                skipped.append(name)
                continue
            if kind == "megadepth":
                name = f"megadepth/{entry['scene']}"
                scene, pairs = read_megadepth(path, entry["scene"], float(entry.get("min_overlap", 0.3)))
            elif kind == "cmu":
                name = f"cmu/slice{entry['slice']}"
                scene, pairs = read_cmu_slice(path, int(entry["slice"]), float(entry.get("min_overlap", 0.3)))
                if init_range is None:
                    init_range = (0.0, 0.0)  # official CMU training starts from the reference pose
            else:
                if "images" in entry:
                    entry["images"] = data_root / entry["images"]
                for key in ("intrinsics", "sequences"):
                    if key in entry:
                        entry[key] = tuple(entry[key])
                scene = load_scene(MapSource(kind, path, **entry), work_dir / name.replace("/", "_"))
        sources.append(Source(name, scene, weight, pairs, tuple(init_range) if init_range is not None else None))
    return sources, skipped
