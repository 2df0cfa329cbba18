"""Map sources: what users have (a COLMAP model, images, known poses, kapture, RGB-D), as a Scene."""

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, List, Optional, Sequence, Tuple

import numpy as np

from pipeline.mapping.depth import densify, rgbd_scene
from pipeline.mapping.image_pairs import PairsConfig
from pipeline.progress import Silent
from pipeline.queries import QueryRecord, read_queries_with_intrinsics
from pipeline.scene import SceneError, name_problem, refuse_duplicates
from pipeline.mapping.readers.colmap import read_colmap, run_sfm, triangulate_known_poses
from pipeline.mapping.readers.bundler import read_bundler
from pipeline.mapping.readers.kapture import read_kapture
from pipeline.mapping.readers.llff import read_llff
from pipeline.mapping.readers.middlebury import read_middlebury
from pipeline.mapping.readers.opensfm import read_opensfm
from pipeline.images import image_files, read_image
from pipeline.mapping.readers.rgbd import read_7scenes, read_pose_txt
from pipeline.mapping.readers.strecha import read_strecha
from pipeline.mapping.readers.transforms import read_transforms
from pipeline.scene import CameraRecord, Scene

# posed images in other formats, triangulated from their poses: kind -> what PATH is
POSED_FORMATS = {
    "strecha": "a Strecha scene folder (images/, gt_dense_cameras/)",
    "kapture": "a kapture folder (sensors/)",
    "llff": "an LLFF scene folder (poses_bounds.npy, images/)",
    "middlebury": "a Middlebury folder (NAME_par.txt beside its images)",
    "bundler": "a Bundler bundle.out (images: --images, default the folder above the bundle's, or list.txt)",
    "opensfm": "an OpenSfM reconstruction.json (images: --images, default images/ beside it)",
    "transforms": "an instant-ngp / nerfstudio transforms.json (images relative to it)",
}
KINDS = ("colmap", "sfm", *POSED_FORMATS, "7scenes", "posetxt")


@dataclass(frozen=True)
class MapSource:
    """Where a map comes from.

    kind: ``colmap`` (model folder ``path`` + ``images``), ``sfm`` (reconstruct
    the images in ``path`` with pycolmap), one of ``POSED_FORMATS`` (known poses
    in that format: SIFT + triangulation), ``7scenes`` (RGB-D frames of ``sequences``),
    ``posetxt`` (``color/``, ``depth/``, ``pose.txt``; needs ``intrinsics`` =
    (fx, fy, cx, cy) in COLMAP convention, ``depth_scale`` and ``depth_ext``).
    rgbd_points: ``tsdf`` or ``frames``. densify: move SfM points onto depth.
    hold_out: image names left out of the map (queries of a held-out split): SfM and
    triangulation never see them; a COLMAP model or RGB-D map drops their observations.
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
    hold_out: Tuple[str, ...] = field(default_factory=tuple)

    def to_dict(self):
        out = {"kind": self.kind, "path": str(self.path), "images": str(self.images) if self.images else None,
               "sequences": list(self.sequences), "rgbd_points": self.rgbd_points, "densify": self.densify,
               "intrinsics": list(self.intrinsics), "depth_scale": self.depth_scale, "depth_ext": self.depth_ext}
        return {**out, "hold_out": list(self.hold_out)} if self.hold_out else out  # as stores without it recorded


# the MapSource fields each kind reads (the plan shows those, not depth settings for Strecha)
SOURCE_FIELDS = {"colmap": ("path", "images", "densify", "hold_out"), "sfm": ("path", "densify", "hold_out"),
                 **{kind: ("path", "images", "densify", "hold_out") for kind in POSED_FORMATS},
                 "7scenes": ("path", "sequences", "rgbd_points", "hold_out"),
                 "posetxt": ("path", "intrinsics", "depth_scale", "depth_ext", "rgbd_points", "hold_out")}


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


def posed_images(kind: str, path: Path, images: Optional[Path] = None) -> Tuple[List, Path]:
    """The posed images of a ``POSED_FORMATS`` source, and the folder their names are relative to.
    Every image is checked as a map needs it (``ImageRecord.check``: a finite rotation, a camera
    that can project): a source that holds one that is not is refused, naming it."""
    found, root = _read_posed(kind, Path(path), images)
    refuse_duplicates(found, path)  # before COLMAP's database, which aborts on one
    for im in found:
        reason = im.check()
        if reason:
            raise SceneError(f"{path}: image {im.name}: {reason}.")
    return found, root


def _read_posed(kind: str, path: Path, images: Optional[Path]) -> Tuple[List, Path]:
    if kind == "strecha":
        return read_strecha(path), path / "images"
    if kind == "kapture":
        return read_kapture(path), path / "sensors" / "records_data"
    if kind == "llff":
        return read_llff(path), path / "images"
    if kind == "middlebury":
        return read_middlebury(path), path
    if kind == "bundler":
        root = Path(images) if images else path.parent.parent
        return read_bundler(path, root), root
    if kind == "opensfm":
        root = Path(images) if images else path.parent / "images"
        return read_opensfm(path, root), root
    if kind == "transforms":
        return read_transforms(path), path.parent
    raise ValueError(f"Unknown posed format {kind!r}; known: {', '.join(POSED_FORMATS)}.")


def check_known(option: str, given: Sequence[str], names: Sequence[str]) -> None:
    """A name given by ``option`` that is none of the source's ``names`` is an error, not ignored: a
    typo would otherwise put a query in the map it is evaluated against, or drop it from a run."""
    unknown = sorted(set(given) - set(names))
    if unknown:
        raise ValueError(f"{option}: {', '.join(unknown[:5])} {'is' if len(unknown) == 1 else 'are'} not among "
                         f"the source's {len(names)} images (e.g. {', '.join(sorted(names)[:3])}).")


def kept(names: Sequence[str], hold_out: Sequence[str]) -> List[bool]:
    """Which of ``names`` stay in the map (``check_known``: each held-out name must be one of them)."""
    check_known("--hold-out", hold_out, names)
    held = set(hold_out)
    return [n not in held for n in names]


def pose_txt_images(source: MapSource) -> List:
    """The RGB-D frames of a ``posetxt`` source, with its intrinsics and depth settings."""
    if len(source.intrinsics) != 4:
        raise ValueError("A posetxt source needs --intrinsics FX FY CX CY (COLMAP convention).")
    path = Path(source.path)
    width, height = read_image(next((path / "color").iterdir())).shape[1::-1]
    camera = CameraRecord("PINHOLE", width, height, tuple(source.intrinsics))
    return read_pose_txt(path, camera, source.depth_scale, source.depth_ext)


def load_scene(source: MapSource, work_dir: Path, pairs: PairsConfig = PairsConfig(),
               progress: Callable = Silent) -> Scene:
    """The Scene of ``source`` without its held-out images; SfM and triangulation write their
    COLMAP files under ``work_dir``, match the image pairs of ``pairs`` and count images and
    pairs with ``progress``."""
    path = Path(source.path)

    def posed(images):  # reconstructed without the held-out images
        return [im for im, keep in zip(images, kept([im.name for im in images], source.hold_out)) if keep]
    if source.kind == "colmap":
        scene = read_colmap(path, source.images or path.parent / "images")
    elif source.kind == "sfm":
        names = image_files(path)
        scene = run_sfm(path, work_dir / "sfm", [n for n, k in zip(names, kept(names, source.hold_out)) if k],
                        pairs=pairs, progress=progress)
    elif source.kind in POSED_FORMATS:
        images, image_root = posed_images(source.kind, path, source.images)
        scene = triangulate_known_poses(posed(images), image_root, work_dir / "triangulation", pairs=pairs,
                                        progress=progress)
    elif source.kind == "7scenes":
        if not source.sequences:
            raise ValueError("A 7scenes source needs --sequences (e.g. 2 3, the official training split).")
        scene = rgbd_scene(posed(read_7scenes(path, source.sequences)), method=source.rgbd_points)
    elif source.kind == "posetxt":
        scene = rgbd_scene(posed(pose_txt_images(source)), method=source.rgbd_points)
    else:
        raise ValueError(f"Unknown map source {source.kind!r}; known: {', '.join(KINDS)}.")
    if source.kind == "colmap" and source.hold_out:
        keep = kept([im.name for im in scene.images], source.hold_out)
        scene = scene.subset([i for i, k in enumerate(keep) if k])
    return densify(scene) if source.densify else scene


QUERY_KINDS = ("list", "7scenes", "posetxt", *POSED_FORMATS, "colmap", "synthetic")


def as_query(image, tags=None) -> QueryRecord:
    """A posed image as a query: its pose is the ground truth."""
    return QueryRecord(image.name, image.path, image.camera, {**image.tags, **dict(tags or {})},
                       np.asarray(image.cam_from_world))


def load_queries(kind: str, path: Path, images: Optional[Path] = None, sequences: Tuple[int, ...] = (),
                 names: Optional[List[str]] = None, intrinsics: Tuple[float, ...] = ()) -> List[QueryRecord]:
    """Queries with ground truth where the data has it.

    ``list``: a queries_with_intrinsics file, images in ``images``; ``7scenes``: frames
    of ``sequences``; ``posetxt``: the colour frames of a ``pose.txt`` folder, with the camera
    ``intrinsics`` (fx, fy, cx, cy); ``kapture`` / ``strecha``: posed images; ``colmap``: a model's
    images (their SfM poses as ground truth); ``synthetic``: the queries of a generated scene
    (the demo's ``outputs/demo/scene``). ``names`` keeps only those queries, each of which must be
    one of the source's (``check_known``).
    """
    path = Path(path)
    if kind == "list":
        if images is None:
            raise ValueError("A query list needs --query-images.")
        queries = read_queries_with_intrinsics(path, images)
    elif kind == "7scenes":
        if not sequences:
            raise ValueError("7scenes queries need --query-sequences (official test split: 1 4).")
        queries = [as_query(im) for im in read_7scenes(path, sequences)]
    elif kind == "posetxt":
        queries = [as_query(im) for im in pose_txt_images(MapSource(kind, path, intrinsics=tuple(intrinsics)))]
    elif kind in POSED_FORMATS:
        queries = [as_query(im) for im in posed_images(kind, path, images)[0]]
    elif kind == "colmap":
        queries = [as_query(im) for im in read_colmap(path, images or path.parent / "images").images]
    elif kind == "synthetic":  # a generated scene (the demo's outputs/demo/scene), with ground truth
        from pipeline.data.synthetic import read_synthetic
        queries = read_synthetic(path)[1]
    else:
        raise ValueError(f"Unknown query source {kind!r}; known: {', '.join(QUERY_KINDS)}.")
    if names is not None:
        check_known("--query-names", names, [q.name for q in queries])
        keep = set(names)
        queries = [q for q in queries if q.name in keep]
    # every source's names are relative paths inside its image folder (pipeline.scene.name_problem)
    return [q if q.error or not name_problem(q.name) else dataclasses.replace(q, error=name_problem(q.name))
            for q in queries]
