"""Query images: names, files, intrinsics and condition tags; retrieval pairs."""

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np

from pixloc.geometry import COLMAP_MODELS

from pipeline.scene import CameraRecord, name_problem
from pipeline.textfiles import InputError, data_lines


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
    first: dict = {}
    for line_no, (name, *fields) in data_lines(path, "query list"):
        if name in first:  # a query's name is its key in every output: the whole list is refused
            raise InputError(f"{path}:{line_no}: query {name} is listed twice (first at line {first[name]}): "
                             "each query once")
        first[name] = line_no
        camera, error = None, None
        spaced = next((k for k, f in enumerate(fields) if f in COLMAP_MODELS), 0)
        if spaced > 0:
            error = (f"{path}:{line_no}: bad query line: the name has spaces "
                     f"({' '.join([name, *fields[:spaced]])!r}); this format separates fields by whitespace: "
                     "rename the file")
        elif name_problem(name):
            error = f"{path}:{line_no}: bad query line: {name_problem(name)}"
        elif len(fields) < 3:
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


def also_in_map(queries: List[QueryRecord], map_names: List[str], map_paths: List[Path]) -> List[str]:
    """The queries that are map images too: the same name, or a file of the same bytes (a query
    localized against itself retrieves itself, and its error says nothing). File sizes are
    compared first; only files of a size that a map image has are hashed."""
    from pipeline.images import file_sha256

    names = set(map_names)
    sizes: Dict[int, List[Path]] = {}
    for p in map_paths:
        try:
            sizes.setdefault(Path(p).stat().st_size, []).append(Path(p))
        except OSError:
            continue
    digests: Dict[Path, str] = {}

    def digest(p: Path) -> str:
        if p not in digests:
            digests[p] = file_sha256(p)
        return digests[p]

    out = []
    for q in queries:
        if q.name in names:
            out.append(q.name)
            continue
        try:
            same_size = sizes.get(q.path.stat().st_size, [])
            if same_size and any(digest(q.path) == digest(p) for p in same_size):
                out.append(q.name)
        except OSError:
            continue
    return out
