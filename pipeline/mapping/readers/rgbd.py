"""RGB-D frames with poses: the 7-Scenes layout and ``pose.txt`` trajectories (slambook)."""

import warnings
from pathlib import Path
from typing import List, Optional, Sequence

import numpy as np

from pipeline.scene import CameraRecord, ImageRecord, SceneError, qvec_to_rotmat

# 7-Scenes practice: colour treated as focal 525, principal point (320, 240);
# the depth sensor (focal 585) is not registered to colour.
SEVEN_SCENES_COLOR = CameraRecord("PINHOLE", 640, 480, (525.0, 525.0, 320.0, 240.0))
SEVEN_SCENES_DEPTH = CameraRecord("PINHOLE", 640, 480, (585.0, 585.0, 320.0, 240.0))


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


def read_7scenes(root, sequences: Sequence[int], tags=None) -> List[ImageRecord]:
    """Frames of ``seq-XX`` folders: colour, depth in millimetres, camera-to-world pose.txt."""
    root = Path(root)
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
            images.append(ImageRecord(
                f"seq-{seq:02d}/{color.name}", color, SEVEN_SCENES_COLOR, _world_to_cam(c2w),
                {"sequence": f"seq-{seq:02d}", **dict(tags or {})},
                depth_path=folder / f"{stem}.depth.png", depth_scale=1e-3, depth_camera=SEVEN_SCENES_DEPTH))
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
