"""Map sources: what users have (a COLMAP model, images, known poses, kapture, RGB-D), as a Scene."""

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional, Tuple

import numpy as np

from pipeline.depth import densify, rgbd_scene
from pipeline.pairs import PairsConfig
from pipeline.queries import QueryRecord, read_queries_with_intrinsics
from pipeline.scene import name_problem
from pipeline.readers.colmap import read_colmap, run_sfm, triangulate_known_poses
from pipeline.readers.kapture import read_kapture
from pipeline.images import read_image
from pipeline.readers.rgbd import read_7scenes, read_pose_txt
from pipeline.readers.strecha import read_strecha
from pipeline.scene import CameraRecord, Scene

KINDS = ("colmap", "sfm", "strecha", "kapture", "7scenes", "posetxt")


@dataclass(frozen=True)
class MapSource:
    """Where a map comes from.

    kind: ``colmap`` (model folder ``path`` + ``images``), ``sfm`` (reconstruct
    the images in ``path`` with pycolmap), ``strecha`` / ``kapture`` (known
    poses: SIFT + triangulation), ``7scenes`` (RGB-D frames of ``sequences``),
    ``posetxt`` (``color/``, ``depth/``, ``pose.txt``; needs ``intrinsics`` =
    (fx, fy, cx, cy) in COLMAP convention, ``depth_scale`` and ``depth_ext``).
    rgbd_points: ``tsdf`` or ``frames``. densify: move SfM points onto depth.
    """

    kind: str
    path: Path
    images: Optional[Path] = None
    sequences: Tuple[int, ...] = field(default_factory=tuple)
    rgbd_points: str = "tsdf"
    densify: bool = False
    intrinsics: Tuple[float, ...] = field(default_factory=tuple)
    depth_scale: float = 1e-3
    depth_ext: str = ".png"

    def to_dict(self):
        return {"kind": self.kind, "path": str(self.path), "images": str(self.images) if self.images else None,
                "sequences": list(self.sequences), "rgbd_points": self.rgbd_points, "densify": self.densify,
                "intrinsics": list(self.intrinsics), "depth_scale": self.depth_scale, "depth_ext": self.depth_ext}


# the MapSource fields each kind reads (the plan shows those, not depth settings for Strecha)
SOURCE_FIELDS = {"colmap": ("path", "images", "densify"), "sfm": ("path", "densify"),
                 "strecha": ("path", "densify"), "kapture": ("path", "densify"),
                 "7scenes": ("path", "sequences", "rgbd_points"),
                 "posetxt": ("path", "intrinsics", "depth_scale", "depth_ext", "rgbd_points")}


def describe_source(source: dict) -> str:
    """'strecha /data/Herz-Jesus-P8' and the fields that kind reads, e.g. 'sequences [2, 3]'."""
    kind = source.get("kind", "?")
    fields = SOURCE_FIELDS.get(kind, tuple(k for k in source if k != "kind"))
    parts = [kind, str(source.get("path"))]
    for key in fields:
        value = source.get(key)
        if key != "path" and value not in (None, [], (), False):
            parts.append(f"{key.replace('_', ' ')} {value}")
    return " ".join(parts[:2]) if len(parts) == 2 else f"{parts[0]} {parts[1]} ({', '.join(parts[2:])})"


def load_scene(source: MapSource, work_dir: Path, pairs: PairsConfig = PairsConfig()) -> Scene:
    """The Scene of ``source``; SfM and triangulation write their COLMAP files under ``work_dir``
    and match the image pairs of ``pairs``."""
    path = Path(source.path)
    if source.kind == "colmap":
        scene = read_colmap(path, source.images or path.parent / "images")
    elif source.kind == "sfm":
        scene = run_sfm(path, work_dir / "sfm", pairs=pairs)
    elif source.kind == "strecha":
        scene = triangulate_known_poses(read_strecha(path), path / "images", work_dir / "triangulation",
                                        pairs=pairs)
    elif source.kind == "kapture":
        scene = triangulate_known_poses(read_kapture(path), path / "sensors" / "records_data",
                                        work_dir / "triangulation", pairs=pairs)
    elif source.kind == "7scenes":
        if not source.sequences:
            raise ValueError("A 7scenes source needs --sequences (e.g. 2 3, the official training split).")
        scene = rgbd_scene(read_7scenes(path, source.sequences), method=source.rgbd_points)
    elif source.kind == "posetxt":
        if len(source.intrinsics) != 4:
            raise ValueError("A posetxt source needs --intrinsics FX FY CX CY (COLMAP convention).")
        width, height = read_image(next((path / "color").iterdir())).shape[1::-1]
        camera = CameraRecord("PINHOLE", width, height, tuple(source.intrinsics))
        images = read_pose_txt(path, camera, source.depth_scale, source.depth_ext)
        scene = rgbd_scene(images, method=source.rgbd_points)
    else:
        raise ValueError(f"Unknown map source {source.kind!r}; known: {', '.join(KINDS)}.")
    return densify(scene) if source.densify else scene


QUERY_KINDS = ("list", "7scenes", "kapture", "strecha", "colmap", "synthetic")


def _as_query(image, tags=None) -> QueryRecord:
    return QueryRecord(image.name, image.path, image.camera, {**image.tags, **dict(tags or {})},
                       np.asarray(image.cam_from_world))


def load_queries(kind: str, path: Path, images: Optional[Path] = None, sequences: Tuple[int, ...] = (),
                 names: Optional[List[str]] = None) -> List[QueryRecord]:
    """Queries with ground truth where the data has it.

    ``list``: a queries_with_intrinsics file, images in ``images``; ``7scenes``: frames
    of ``sequences``; ``kapture`` / ``strecha``: posed images; ``colmap``: a model's
    images (their SfM poses as ground truth); ``synthetic``: the queries of a generated scene
    (the demo's ``outputs/demo/scene``). ``names`` keeps only those queries.
    """
    path = Path(path)
    if kind == "list":
        if images is None:
            raise ValueError("A query list needs --query-images.")
        queries = read_queries_with_intrinsics(path, images)
    elif kind == "7scenes":
        if not sequences:
            raise ValueError("7scenes queries need --query-sequences (official test split: 1 4).")
        queries = [_as_query(im) for im in read_7scenes(path, sequences)]
    elif kind == "kapture":
        queries = [_as_query(im) for im in read_kapture(path)]
    elif kind == "strecha":
        queries = [_as_query(im) for im in read_strecha(path)]
    elif kind == "colmap":
        queries = [_as_query(im) for im in read_colmap(path, images or path.parent / "images").images]
    elif kind == "synthetic":  # a generated scene (the demo's outputs/demo/scene), with ground truth
        from pipeline.synthetic import read_synthetic
        queries = read_synthetic(path)[1]
    else:
        raise ValueError(f"Unknown query source {kind!r}; known: {', '.join(QUERY_KINDS)}.")
    if names is not None:
        keep = set(names)
        queries = [q for q in queries if q.name in keep]
    # every source's names are relative paths inside its image folder (pipeline.scene.name_problem)
    return [q if q.error or not name_problem(q.name) else dataclasses.replace(q, error=name_problem(q.name))
            for q in queries]
