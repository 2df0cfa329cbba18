"""RGB-D frames with poses: the 7-Scenes layout and ``pose.txt`` trajectories (slambook)."""

import warnings
from pathlib import Path
from typing import List, Optional, Sequence

import numpy as np

from pixloc.geometry import Pose

from pipeline.scene import CameraRecord, ImageRecord, SceneError, qvec_to_rotmat

# 7-Scenes practice: colour treated as focal 525, principal point (320, 240);
# the depth sensor (focal 585) is not registered to colour.
SEVEN_SCENES_COLOR = CameraRecord("PINHOLE", 640, 480, (525.0, 525.0, 320.0, 240.0))
SEVEN_SCENES_DEPTH = CameraRecord("PINHOLE", 640, 480, (585.0, 585.0, 320.0, 240.0))
# The poses of 7-Scenes are the depth sensor's. Its Kinect (v1) has the colour camera 2.5 cm
# beside the infrared one, along the sensors' x axis: the documented baseline of the device, not
# a fit to the frames (tests/pipeline/test_readers.py checks that it makes the colour of the map
# frames warped through depth agree better than no offset does). The colour camera's centre is at
# x = +2.5 cm in the depth frame, so colour_from_depth = [I | (-0.025, 0, 0)].
KINECT_COLOR_FROM_DEPTH = np.array([[1.0, 0.0, 0.0, -0.025], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])


def _world_to_cam(c2w: np.ndarray) -> np.ndarray:
    R, t = c2w[:3, :3], c2w[:3, 3]
    return np.concatenate([R.T, (-R.T @ t)[:, None]], 1)


def _matrix_file(path: Path) -> np.ndarray:
    """A 4x4 camera-to-world matrix file; SceneError naming it when it is not one."""
    try:
        with warnings.catch_warnings():  # an empty file: our error below says it, with the file
            warnings.simplefilter("ignore", UserWarning)
            values = np.loadtxt(path)
    except (ValueError, UnicodeDecodeError) as e:
        raise SceneError(f"{path}: not a 4x4 pose file ({e})") from None
    if values.size != 16:
        raise SceneError(f"{path}: a pose file holds 16 numbers (4x4), not {values.size}")
    return values.reshape(4, 4)


CALIBRATION_FILE = "color_from_depth.txt"  # in a 7-Scenes root: overrides the Kinect default


def color_from_depth_of(root: Path) -> np.ndarray:
    """The calibration of a 7-Scenes folder: its ``color_from_depth.txt`` (a 3x4 or 4x4 matrix, the
    rigid transform from the depth sensor's frame to the colour camera's, metres) if it has one,
    else the Kinect's baseline (``KINECT_COLOR_FROM_DEPTH``)."""
    path = Path(root) / CALIBRATION_FILE
    if not path.is_file():
        return KINECT_COLOR_FROM_DEPTH
    try:
        values = np.loadtxt(path, ndmin=2)
    except (ValueError, UnicodeDecodeError) as e:
        raise SceneError(f"{path}: not a 3x4 or 4x4 matrix ({e})") from None
    R = values[:3, :3] if values.shape in ((3, 4), (4, 4)) else None
    if R is None or not np.isfinite(values).all() or not np.allclose(R @ R.T, np.eye(3), atol=1e-4) \
            or np.linalg.det(R) < 0:
        raise SceneError(f"{path}: expected a rigid transform as a 3x4 or 4x4 matrix [R | t], got "
                         f"{'x'.join(map(str, values.shape))} values that are not one")
    return values[:3]


def read_7scenes(root, sequences: Sequence[int], tags=None, color_from_depth="auto") -> List[ImageRecord]:
    """Frames of ``seq-XX`` folders: colour, depth in millimetres, camera-to-world pose.txt (of the
    depth sensor). Each frame's pose is the colour camera's: ``color_from_depth`` (3, 4) applied to
    the depth sensor's; "auto": the folder's calibration (``color_from_depth_of``); None: the
    colour camera placed at the depth sensor's pose."""
    root = Path(root)
    if isinstance(color_from_depth, str):
        color_from_depth = color_from_depth_of(root)
    C = None if color_from_depth is None else np.asarray(color_from_depth, np.float64).reshape(3, 4)
    images = []
    for seq in sequences:
        folder = root / f"seq-{seq:02d}"
        frames = sorted(folder.glob("frame-*.color.jpg"))
        if not frames:
            raise SceneError(f"No frames in {folder}.")
        for color in frames:
            stem = color.name[: -len(".color.jpg")]
            pose_file = folder / f"{stem}.pose.txt"
            c2w = _matrix_file(pose_file) if pose_file.is_file() else np.full((4, 4), np.nan)
            pose = _world_to_cam(c2w)
            if C is not None:  # colour_from_world = colour_from_depth @ depth_from_world
                pose = (Pose.from_matrix(C) @ Pose.from_matrix(pose)).to_matrix()
            images.append(ImageRecord(
                f"seq-{seq:02d}/{color.name}", color, SEVEN_SCENES_COLOR, pose,
                {"sequence": f"seq-{seq:02d}", **dict(tags or {})},
                depth_path=folder / f"{stem}.depth.png", depth_scale=1e-3, depth_camera=SEVEN_SCENES_DEPTH,
                color_from_depth=C))
    return images


def read_pose_txt(root, camera: CameraRecord, depth_scale: float, depth_ext: str = ".png",
                  depth_camera: Optional[CameraRecord] = None, tags=None) -> List[ImageRecord]:
    """``color/N.png``, ``depth/N<ext>`` and ``pose.txt`` (line N: tx ty tz qx qy qz qw, camera-to-world)."""
    root = Path(root)
    path = root / "pose.txt"
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            poses = np.loadtxt(path, ndmin=2)
    except (ValueError, OSError, UnicodeDecodeError) as e:
        raise SceneError(f"{path}: not a pose file of 'tx ty tz qx qy qz qw' lines ({e})") from None
    if poses.size == 0 or poses.shape[1] != 7:
        raise SceneError(f"{path}: expected 7 numbers a line (tx ty tz qx qy qz qw), got {poses.shape[1]}")
    images = []
    for i, (tx, ty, tz, qx, qy, qz, qw) in enumerate(poses, start=1):
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = qvec_to_rotmat([qw, qx, qy, qz]), (tx, ty, tz)
        images.append(ImageRecord(f"color/{i}.png", root / "color" / f"{i}.png", camera, _world_to_cam(c2w),
                                  dict(tags or {}), depth_path=root / "depth" / f"{i}{depth_ext}",
                                  depth_scale=depth_scale, depth_camera=depth_camera))
    return images
