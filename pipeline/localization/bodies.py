"""Bodies in the localizer: the images of a rig at one instant, or of a chunk of frames, refined as one
pose (``pixloc.optim.bodies``), and what a body's images report."""

from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

import numpy as np

from pixloc.geometry import Pose
from pixloc.optim import Bodies

from pipeline.queries import QueryRecord

def split_bodies(groups: Dict[Tuple, List]) -> None:
    """Fail the images of a body that fell into different LM batches (feature maps of different sizes, or
    camera models of different kinds): a body is solved in one batch. ``groups``: the localizer's batches of
    its ``LevelState`` (which imports this module)."""
    where: Dict[str, set] = {}
    for key, group in groups.items():
        for st in group:
            if st.body is not None:
                where.setdefault(st.body.key, set()).add(key)
    split = {body for body, keys in where.items() if len(keys) > 1}
    for group in groups.values():
        for st in group:
            if st.body is not None and st.body.key in split:
                st.active = False
                st.result.reason = (f"the images of body {st.body.key!r} give feature maps of different sizes or "
                                    "cameras of different kinds: a body is refined in one batch, of one size")


def group_bodies(group: List) -> Optional[Bodies]:
    """The bodies of an LM batch (``pixloc.optim.bodies``): the images of one body together, every other
    query its own; None where no image of the batch belongs to a body."""
    if all(st.body is None for st in group):
        return None
    eye = np.eye(4)[:3]
    keys = [("body", st.body.key) if st.body is not None else ("query", b) for b, st in enumerate(group)]
    cams = [Pose.from_matrix(st.body.cam_from_body if st.body is not None else eye).float() for st in group]
    return Bodies.of(keys, Pose.stack(cams))


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a @ b of two 3 x 4 poses."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.concatenate([a[:, :3] @ b[:, :3], (a[:, :3] @ b[:, 3] + a[:, 3])[:, None]], 1)


def invert(a: np.ndarray) -> np.ndarray:
    """The inverse of a 3 x 4 pose."""
    a = np.asarray(a, np.float64)
    return np.concatenate([a[:, :3].T, (-a[:, :3].T @ a[:, 3])[:, None]], 1)


@dataclass(frozen=True)
class Frame:
    """The images of one body: a rig at one instant (``key``: rig and timestamp) or a chunk of frames;
    ``cam_from_body[i]`` (3 x 4) is image i's camera in the body's frame."""

    key: str
    queries: Tuple[QueryRecord, ...]
    cam_from_body: Tuple[np.ndarray, ...]
    tags: dict = field(default_factory=dict)

    def __post_init__(self):
        if not self.queries or len(self.queries) != len(self.cam_from_body):
            raise ValueError(f"frame {self.key!r}: one cam_from_body per image, and at least one image.")

    def body_gt(self) -> Optional[np.ndarray]:
        """The body's ground-truth pose from its first image with one, or None."""
        for q, C in zip(self.queries, self.cam_from_body):
            if q.cam_from_world_gt is not None:
                return compose(invert(C), q.cam_from_world_gt)
        return None
