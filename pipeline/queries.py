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
    camera: Optional[CameraRecord]
    tags: Dict[str, str] = field(default_factory=dict)
    cam_from_world_gt: Optional[np.ndarray] = None
    error: Optional[str] = None  # why this query cannot run (a bad line of its list): it fails with it
    notes: tuple = ()  # what was adjusted to run it (e.g. intrinsics rescaled to the file), into its record
    # references found by a retrieval stage run before sharding: {"dbs": [names], "similarity": [..] or None}
    retrieved: Optional[Dict] = None


def read_queries_with_intrinsics(path, image_dir, tags=None) -> List[QueryRecord]:
    """The hloc/PixLoc format: ``name MODEL width height params...`` per line.

    A bad line (too few fields, numbers that do not parse, a parameter count that does not
    fit the model) does not stop the list: its query carries ``error`` = ``file:line: reason``
    and fails with it."""
    queries = []
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"Query list {path} does not exist.")
    for line_no, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        name, *fields = line.split()
        camera, error = None, None
        if len(fields) < 3:
            error = f"{path}:{line_no}: bad query line: expected 'name MODEL width height params...'"
        else:
            model, w, h, *params = fields
            try:
                camera = CameraRecord(model, int(w), int(h), tuple(float(p) for p in params))
            except ValueError as e:
                error = f"{path}:{line_no}: bad query line: {e}"
            else:
                reason = camera.check()
                if reason:
                    camera, error = None, f"{path}:{line_no}: bad query line: {reason}"
        queries.append(QueryRecord(name, Path(image_dir) / name, camera, dict(tags or {}), error=error))
    return queries


def read_pairs(path) -> Dict[str, List[str]]:
    """hloc/PixLoc retrieval pairs ``query reference`` per line, kept in ranked order."""
    pairs: Dict[str, List[str]] = defaultdict(list)
    for line in Path(path).read_text().splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            q, r = line.split()[:2]
            pairs[q].append(r)
    return dict(pairs)
