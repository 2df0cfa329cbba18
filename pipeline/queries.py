"""Query images: names, files, intrinsics and condition tags; retrieval pairs."""

from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np

from .scene import CameraRecord, SceneError


@dataclass
class QueryRecord:
    """A query image: name (as written in outputs), file, camera, condition tags, optional
    ground-truth cam_from_world (3, 4) for evaluation."""

    name: str
    path: Path
    camera: CameraRecord
    tags: Dict[str, str] = field(default_factory=dict)
    cam_from_world_gt: Optional[np.ndarray] = None


def read_queries_with_intrinsics(path, image_dir, tags=None) -> List[QueryRecord]:
    """The hloc/PixLoc format: ``name MODEL width height params...`` per line."""
    queries = []
    for line_no, line in enumerate(Path(path).read_text().splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        name, model, w, h, *params = line.split()
        try:
            camera = CameraRecord(model, int(w), int(h), tuple(float(p) for p in params))
        except ValueError as e:
            raise SceneError(f"{path}:{line_no}: bad query line: {e}") from None
        queries.append(QueryRecord(name, Path(image_dir) / name, camera, dict(tags or {})))
    return queries


def read_pairs(path) -> Dict[str, List[str]]:
    """hloc/PixLoc retrieval pairs ``query reference`` per line, kept in ranked order."""
    pairs: Dict[str, List[str]] = defaultdict(list)
    for line in Path(path).read_text().splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            q, r = line.split()[:2]
            pairs[q].append(r)
    return dict(pairs)
