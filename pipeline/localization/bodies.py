"""Bodies in the localizer: the images of a rig at one instant, or of a chunk of frames, refined as one
pose (``pixloc.optim.bodies``), and what a body's images report."""

from typing import Dict, List, Optional, Tuple

import numpy as np

from pixloc.geometry import Pose
from pixloc.optim import Bodies

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


