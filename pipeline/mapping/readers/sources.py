"""Map and query sources: what users have (a COLMAP model, images, known poses in another format,
RGB-D frames, a query list), as a ``Scene`` to build a map from or as queries.

The registry ``SOURCES`` (``build-map KIND`` and ``localize QUERY_KIND`` choose an entry): an entry is
a class registered under its name whose attributes say what it is (``help``: what PATH is;
``reads``: the ``MapSource`` fields it uses; ``maps`` / ``queries``: whether it can be a map's or
the queries' source; ``reconstructs``: the reconstruction stage a map from it runs first, if any)
and whose methods read it:

- ``images(source)``: its posed images (their poses the ground truth of queries);
- ``scene(source, work_dir, pairs, tasks)``: the Scene a map is built from;
- ``query_records(source)``: its images as queries.

A format of posed images (``PosedFormat``) only reads its files (``read``): the map is triangulated
from its poses (SIFT, matching, triangulation), its images are queries with ground truth. A new
source is one class here (its reader in its own module beside this one).
"""

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, ClassVar, List, Optional, Sequence, Tuple

import numpy as np

from pipeline.images import image_files, read_image
from pipeline.mapping.image_pairs import PairsConfig
from pipeline.mapping.structure import Tasks
from pipeline.progress import Silent
from pipeline.queries import QueryRecord, read_queries_with_intrinsics
from pipeline.registry import Registry
from pipeline.scene import CameraRecord, ImageRecord, Scene, SceneError, name_problem, refuse_duplicates


@dataclass(frozen=True)
class MapSource:
    """Where a map (or the queries) comes from.

    kind: an entry of ``SOURCES``; path: what its ``help`` says; images: the image folder of a
    COLMAP model, a Bundler bundle or an OpenSfM reconstruction; sequences: 7-Scenes sequences;
    rgbd_points: ``tsdf`` or ``frames``; densify: move SfM points onto depth; intrinsics (fx, fy,
    cx, cy, COLMAP convention), depth_scale and depth_ext: a ``posetxt`` folder's; hold_out: image
    names left out of the map (queries of a held-out split): SfM and triangulation never see them;
    a COLMAP model or RGB-D map drops their observations; mapper: an ``sfm`` source's SfM
    (``pipeline.mapping.readers.colmap.MAPPERS``).
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
    mapper: str = "incremental"

    def to_dict(self):
        out = {"kind": self.kind, "path": str(self.path), "images": str(self.images) if self.images else None,
               "sequences": list(self.sequences), "rgbd_points": self.rgbd_points, "densify": self.densify,
               "intrinsics": list(self.intrinsics), "depth_scale": self.depth_scale, "depth_ext": self.depth_ext}
        out = {**out, "hold_out": list(self.hold_out)} if self.hold_out else out  # as stores without it recorded
        return {**out, "mapper": self.mapper} if self.mapper != "incremental" else out

    @property
    def format(self) -> "SourceFormat":
        """Its entry of ``SOURCES`` (an unknown kind is refused with the known ones)."""
        return SOURCES.entry(self.kind)()


SOURCES = Registry("source", tag="kind")


@dataclass(frozen=True)
class SourceFormat:
    """One kind of source (see the module docstring)."""

    name: ClassVar[str]
    help: ClassVar[str] = ""
    reads: ClassVar[Tuple[str, ...]] = ("path", "images", "densify", "hold_out")
    maps: ClassVar[bool] = True
    queries: ClassVar[bool] = True
    reconstructs: ClassVar[Optional[str]] = None
    units: ClassVar[str] = "scene units"  # of its poses: "m", or "SfM units" (an SfM model's: scale unknown)

    def images(self, source: MapSource) -> List[ImageRecord]:
        raise ValueError(f"A {self.name} source has no posed images to read.")

    def scene(self, source: MapSource, work_dir: Path, pairs: PairsConfig, tasks: Tasks) -> Scene:
        raise ValueError(f"A {self.name} source cannot be a map's: use one of {', '.join(map_kinds())}.")

    def query_records(self, source: MapSource) -> List[QueryRecord]:
        return [as_query(im) for im in self.images(source)]


def map_units(source: dict) -> str:
    """The unit of a map's poses from its recorded source (``MapSource.to_dict``): 'm', 'SfM units'
    (scale unknown), or 'scene units' for a source that does not say (a store built through the library)."""
    entry = SOURCES.get(source.get("kind"))
    return entry.units if entry is not None else "scene units"


def map_kinds() -> List[str]:
    return [name for name, entry in SOURCES.items() if entry.maps]


def query_kinds() -> List[str]:
    return [name for name, entry in SOURCES.items() if entry.queries]


def as_query(image, tags=None) -> QueryRecord:
    """A posed image as a query: its pose is the ground truth."""
    return QueryRecord(image.name, image.path, image.camera, {**image.tags, **dict(tags or {})},
                       np.asarray(image.cam_from_world))


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


def without_held_out(images: List[ImageRecord], source: MapSource) -> List[ImageRecord]:
    return [im for im, keep in zip(images, kept([im.name for im in images], source.hold_out)) if keep]


@SOURCES.register("colmap")
@dataclass(frozen=True)
class Colmap(SourceFormat):
    help: ClassVar[str] = "a COLMAP model folder (images: --images, default PATH/../images)"
    units: ClassVar[str] = "SfM units"

    def model(self, source: MapSource) -> Scene:
        from pipeline.mapping.readers.colmap import read_colmap
        return read_colmap(Path(source.path), source.images or Path(source.path).parent / "images")

    def images(self, source):
        return self.model(source).images

    def scene(self, source, work_dir, pairs, tasks):
        scene = self.model(source)
        if source.hold_out:
            keep = kept([im.name for im in scene.images], source.hold_out)
            scene = scene.subset([i for i, k in enumerate(keep) if k])
        return scene


@SOURCES.register("sfm")
@dataclass(frozen=True)
class StructureFromMotion(SourceFormat):
    help: ClassVar[str] = "an image folder, reconstructed by SfM (pycolmap)"
    units: ClassVar[str] = "SfM units"
    reads: ClassVar[Tuple[str, ...]] = ("path", "densify", "hold_out", "mapper")
    queries: ClassVar[bool] = False
    reconstructs: ClassVar[Optional[str]] = "SIFT, matching and SfM"

    def scene(self, source, work_dir, pairs, tasks):
        from pipeline.mapping.readers.colmap import run_sfm
        names = image_files(Path(source.path))
        return run_sfm(Path(source.path), work_dir / "sfm", [n for n, k in zip(names, kept(names, source.hold_out))
                                                            if k], pairs=pairs, tasks=tasks, mapper=source.mapper)


@dataclass(frozen=True)
class PosedFormat(SourceFormat):
    """Images with known poses in a format of their own: triangulated from the poses."""

    reconstructs: ClassVar[Optional[str]] = "SIFT, matching and triangulation from the known poses"

    def read(self, path: Path, images: Optional[Path]) -> Tuple[List[ImageRecord], Path]:
        """The format's images and the folder their names are relative to."""
        raise NotImplementedError

    def posed(self, path: Path, images: Optional[Path] = None) -> Tuple[List[ImageRecord], Path]:
        """``read``, every image checked as a map needs it (``ImageRecord.check``: a finite rotation,
        a camera that can project): a source holding one that is not is refused, naming it."""
        found, root = self.read(Path(path), images)
        refuse_duplicates(found, path)  # before COLMAP's database, which aborts on one
        for im in found:
            reason = im.check()
            if reason:
                raise SceneError(f"{path}: image {im.name}: {reason}.")
        return found, root

    def images(self, source):
        return self.posed(Path(source.path), source.images)[0]

    def scene(self, source, work_dir, pairs, tasks):
        from pipeline.mapping.readers.colmap import triangulate_known_poses
        images, root = self.posed(Path(source.path), source.images)
        return triangulate_known_poses(without_held_out(images, source), root, work_dir / "triangulation",
                                       pairs=pairs, tasks=tasks)


@SOURCES.register("strecha")
@dataclass(frozen=True)
class Strecha(PosedFormat):
    help: ClassVar[str] = "a Strecha scene folder (images/, gt_dense_cameras/)"
    units: ClassVar[str] = "m"

    def read(self, path, images):
        from pipeline.mapping.readers.strecha import read_strecha
        return read_strecha(path), path / "images"


@SOURCES.register("kapture")
@dataclass(frozen=True)
class Kapture(PosedFormat):
    help: ClassVar[str] = "a kapture folder (sensors/)"
    units: ClassVar[str] = "m"

    def read(self, path, images):
        from pipeline.mapping.readers.kapture import read_kapture
        return read_kapture(path), path / "sensors" / "records_data"


@SOURCES.register("llff")
@dataclass(frozen=True)
class Llff(PosedFormat):
    help: ClassVar[str] = "an LLFF scene folder (poses_bounds.npy, images/)"
    units: ClassVar[str] = "SfM units"

    def read(self, path, images):
        from pipeline.mapping.readers.llff import read_llff
        return read_llff(path), path / "images"


@SOURCES.register("middlebury")
@dataclass(frozen=True)
class Middlebury(PosedFormat):
    help: ClassVar[str] = "a Middlebury folder (NAME_par.txt beside its images)"

    def read(self, path, images):
        from pipeline.mapping.readers.middlebury import read_middlebury
        return read_middlebury(path), path


@SOURCES.register("bundler")
@dataclass(frozen=True)
class Bundler(PosedFormat):
    help: ClassVar[str] = "a Bundler bundle.out (images: --images, default the folder above the bundle's, or list.txt)"
    units: ClassVar[str] = "SfM units"

    def read(self, path, images):
        from pipeline.mapping.readers.bundler import read_bundler
        root = Path(images) if images else path.parent.parent
        return read_bundler(path, root), root


@SOURCES.register("opensfm")
@dataclass(frozen=True)
class OpenSfM(PosedFormat):
    help: ClassVar[str] = "an OpenSfM reconstruction.json (images: --images, default images/ beside it)"
    units: ClassVar[str] = "SfM units"

    def read(self, path, images):
        from pipeline.mapping.readers.opensfm import read_opensfm
        root = Path(images) if images else path.parent / "images"
        return read_opensfm(path, root), root


@SOURCES.register("transforms")
@dataclass(frozen=True)
class Transforms(PosedFormat):
    help: ClassVar[str] = "an instant-ngp / nerfstudio transforms.json (images relative to it)"
    units: ClassVar[str] = "SfM units"

    def read(self, path, images):
        from pipeline.mapping.readers.transforms import read_transforms
        return read_transforms(path), path.parent


@SOURCES.register("posetable")
@dataclass(frozen=True)
class PoseList(PosedFormat):
    """A plain list of ``NAME QW QX QY QZ TX TY TZ`` (cam_from_world, COLMAP convention; an optional
    ninth field: the image's camera id) with a COLMAP ``cameras.txt`` beside it (``CAMERA_ID MODEL
    WIDTH HEIGHT PARAMS...``): one camera for every image, or the one each line names."""

    help: ClassVar[str] = ("a list of NAME QW QX QY QZ TX TY TZ [CAMERA_ID] with a COLMAP cameras.txt beside it "
                           "(images: --images, default the list's folder)")

    def read(self, path, images):
        from pipeline.textfiles import InputError, data_lines, pose_from_line
        cameras_file, root = path.parent / "cameras.txt", Path(images) if images else path.parent
        cameras = {}
        for line_no, fields in data_lines(cameras_file, "COLMAP cameras file"):
            try:
                cameras[fields[0]] = CameraRecord(fields[1], int(fields[2]), int(fields[3]),
                                                  tuple(float(v) for v in fields[4:]))
            except (IndexError, ValueError):
                raise InputError(f"{cameras_file}:{line_no}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...', "
                                 f"got {' '.join(fields)!r}") from None
        found = []
        for line_no, (name, *fields) in data_lines(path, "pose list"):
            where = f"{path}:{line_no}"
            camera_id = fields.pop() if len(fields) == 8 else next(iter(cameras)) if len(cameras) == 1 else None
            if camera_id not in cameras:
                raise InputError(f"{where}: " + (f"camera {camera_id} is not in {cameras_file}" if camera_id else
                                                 f"{cameras_file} holds {len(cameras)} cameras: give each image's "
                                                 "camera id after its pose"))
            found.append(ImageRecord(name, root / name, cameras[camera_id], pose_from_line(fields, where),
                                     origin=where))
        return found, root


@SOURCES.register("7scenes")
@dataclass(frozen=True)
class SevenScenes(SourceFormat):
    help: ClassVar[str] = "the 7-Scenes dataset root (its frames of --sequences)"
    reads: ClassVar[Tuple[str, ...]] = ("path", "sequences", "rgbd_points", "hold_out")
    units: ClassVar[str] = "m"

    def images(self, source):
        from pipeline.mapping.readers.rgbd import read_7scenes
        if not source.sequences:
            raise ValueError("A 7scenes source needs its sequences: --sequences for a map (e.g. 2 3, the official "
                             "training split), --query-sequences for queries (official test split: 1 4).")
        return read_7scenes(Path(source.path), source.sequences)

    def scene(self, source, work_dir, pairs, tasks):
        from pipeline.mapping.depth import rgbd_scene
        return rgbd_scene(without_held_out(self.images(source), source), method=source.rgbd_points)


@SOURCES.register("posetxt")
@dataclass(frozen=True)
class PoseTxt(SourceFormat):
    help: ClassVar[str] = "the folder of color/, depth/, pose.txt (--intrinsics)"
    reads: ClassVar[Tuple[str, ...]] = ("path", "intrinsics", "depth_scale", "depth_ext", "rgbd_points", "hold_out")
    units: ClassVar[str] = "m"

    def images(self, source):
        from pipeline.mapping.readers.rgbd import read_pose_txt
        if len(source.intrinsics) != 4:
            raise ValueError("A posetxt source needs --intrinsics FX FY CX CY (COLMAP convention).")
        path = Path(source.path)
        width, height = read_image(next((path / "color").iterdir())).shape[1::-1]
        camera = CameraRecord("PINHOLE", width, height, tuple(source.intrinsics))
        return read_pose_txt(path, camera, source.depth_scale, source.depth_ext)

    def scene(self, source, work_dir, pairs, tasks):
        from pipeline.mapping.depth import rgbd_scene
        return rgbd_scene(without_held_out(self.images(source), source), method=source.rgbd_points)


@SOURCES.register("list")
@dataclass(frozen=True)
class QueryList(SourceFormat):
    help: ClassVar[str] = "a query list with intrinsics (name MODEL width height params..., images: --query-images)"
    maps: ClassVar[bool] = False

    def query_records(self, source):
        if source.images is None:
            raise ValueError("A query list needs --query-images.")
        return read_queries_with_intrinsics(Path(source.path), source.images)


@SOURCES.register("synthetic")
@dataclass(frozen=True)
class Synthetic(SourceFormat):
    help: ClassVar[str] = "a generated scene (the demo's outputs/demo/scene), with ground truth"
    units: ClassVar[str] = "m"
    maps: ClassVar[bool] = False

    def query_records(self, source):
        from pipeline.data.synthetic import read_synthetic
        return read_synthetic(Path(source.path))[1]


def posed_images(kind: str, path: Path, images: Optional[Path] = None) -> Tuple[List[ImageRecord], Path]:
    """The checked posed images of a ``PosedFormat`` source, and the folder their names are relative to."""
    entry = SOURCES.entry(kind)()
    if not isinstance(entry, PosedFormat):
        raise ValueError(f"{kind!r} is not a format of posed images; those are: "
                         f"{', '.join(n for n, e in SOURCES.items() if issubclass(e, PosedFormat))}.")
    return entry.posed(Path(path), images)


def load_scene(source: MapSource, work_dir: Path, pairs: PairsConfig = PairsConfig(),
               progress: Callable = Silent, tasks: Optional[Tasks] = None) -> Scene:
    """The Scene of ``source`` without its held-out images; SfM and triangulation write their
    COLMAP files under ``work_dir``, match the image pairs of ``pairs``, run their SIFT and
    matching shards by ``tasks`` (``pipeline.mapping.structure``; in this process by default)
    and count images and pairs with ``progress`` (or ``tasks.progress``)."""
    scene = source.format.scene(source, Path(work_dir), pairs, tasks or Tasks(progress=progress))
    if source.densify:
        from pipeline.mapping.depth import densify
        scene = densify(scene)
    return scene


def load_queries(kind: str, path: Path, images: Optional[Path] = None, sequences: Tuple[int, ...] = (),
                 names: Optional[List[str]] = None, intrinsics: Tuple[float, ...] = ()) -> List[QueryRecord]:
    """The queries of a source of kind ``kind`` (its entry's ``query_records``), with ground truth
    where the data has it. ``names`` keeps only those queries, each of which must be one of the
    source's (``check_known``)."""
    entry = SOURCES.entry(kind)
    if not entry.queries:
        raise ValueError(f"A {kind} source cannot give queries: use one of {', '.join(query_kinds())}.")
    queries = entry().query_records(MapSource(kind, Path(path), images, tuple(sequences),
                                              intrinsics=tuple(intrinsics)))
    if names is not None:
        check_known("--query-names", names, [q.name for q in queries])
        keep = set(names)
        queries = [q for q in queries if q.name in keep]
    # every source's names are relative paths inside its image folder (pipeline.scene.name_problem)
    return [q if q.error or not name_problem(q.name) else dataclasses.replace(q, error=name_problem(q.name))
            for q in queries]


def describe_source(source: dict) -> str:
    """'strecha /data/Herz-Jesus-P8' and the fields that kind reads, e.g. 'sequences [2, 3]'."""
    kind = source.get("kind", "?")
    entry = SOURCES.get(kind)
    fields = entry.reads if entry is not None else tuple(k for k in source if k != "kind")
    parts = [kind, str(source.get("path"))]
    for key in fields:
        value = source.get(key)
        if key != "path" and value not in (None, [], (), False):
            parts.append(f"{key.replace('_', ' ')} {value}")
    return " ".join(parts[:2]) if len(parts) == 2 else f"{parts[0]} {parts[1]} ({', '.join(parts[2:])})"
