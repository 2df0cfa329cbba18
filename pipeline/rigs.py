"""The rig inputs of a localization: which cameras a rig has, and which query images were taken together.

A **rig file** gives each camera's pose in its rig, one per line (kapture's ``rigs.txt`` reads as is;
commas or spaces separate the fields)::

    rig_id sensor_id qw qx qy qz tx ty tz

with (q, t) the camera's ``cam_from_rig`` (kapture's convention: camera_from_world = cam_from_rig @
rig_from_world). A **frames file** says which query image is which camera of which rig frame::

    image_name rig_id frame_id sensor_id

The images of one (rig_id, frame_id) are localized as one body (``pipeline.localization.rigs``); a query
that no line names is localized alone. Every error names its file and line: an image that is not in the
query list, a rig or a sensor that the rig file does not define, an image or a (frame, sensor) given twice.

A **sequence** is given by an odometry file, one frame per line in the order taken::

    image_name qw qx qy qz tx ty tz

with (q, t) the frame's cam_from_odom (its pose in the odometry's own frame, which may drift); its frames
are cut into chunks of ``chunk`` consecutive lines, each localized as one body whose frame is its first
image's camera (cam_from_body = cam_from_odom @ first_from_odom^-1).
"""

from typing import Dict, List, Tuple

import numpy as np

from pipeline.localization.bodies import Frame, compose, invert
from pipeline.queries import QueryRecord
from pipeline.textfiles import InputError, data_lines, pose_from_line

Rigs = Dict[str, Dict[str, np.ndarray]]  # rig_id -> sensor_id -> cam_from_rig (3 x 4)
IDENTITY = np.eye(4)[:3]


def _lines(path, what: str):
    """(file:line, fields) with commas read as separators."""
    for line_no, fields in data_lines(path, what):
        yield f"{path}:{line_no}", " ".join(fields).replace(",", " ").split()


def read_rigs(path) -> Rigs:
    """The rigs of a rig file (see the module docstring); InputError at the first bad line."""
    rigs: Rigs = {}
    first: Dict[Tuple[str, str], str] = {}
    for where, fields in _lines(path, "rig file"):
        if len(fields) != 9:
            raise InputError(f"{where}: expected 'rig_id sensor_id qw qx qy qz tx ty tz' (9 fields), "
                             f"got {len(fields)}")
        rig, sensor = fields[:2]
        if (rig, sensor) in first:
            raise InputError(f"{where}: camera {sensor!r} of rig {rig!r} is defined twice "
                             f"(first at {first[rig, sensor]})")
        first[rig, sensor] = where
        rigs.setdefault(rig, {})[sensor] = pose_from_line(fields[2:], where)
    if not rigs:
        raise InputError(f"{path}: the rig file defines no rig")
    return rigs


def read_frames(path, queries: List[QueryRecord], rigs: Rigs, listed_only: bool = False) -> List[Frame]:
    """The bodies to localize: a ``Frame`` per (rig, frame) of the frames file, its images in the order of
    their lines, then one frame of its own for each query that no line names (see the module docstring).
    ``listed_only``: lines of images that are not among ``queries`` are passed over (a shard's part of a file
    read whole before)."""
    by_name = {q.name: q for q in queries}
    named: Dict[str, str] = {}
    slots: Dict[Tuple[str, str, str], str] = {}
    members: Dict[Tuple[str, str], List[Tuple[QueryRecord, np.ndarray]]] = {}
    for where, fields in _lines(path, "frames file"):
        if len(fields) != 4:
            raise InputError(f"{where}: expected 'image_name rig_id frame_id sensor_id' (4 fields), "
                             f"got {len(fields)}")
        name, rig, frame, sensor = fields
        if listed_only and name not in by_name:
            continue
        if name not in by_name:
            raise InputError(f"{where}: {name!r} is not a query of the list")
        if name in named:
            raise InputError(f"{where}: {name!r} is given twice (first at {named[name]}): an image is one camera "
                             "of one frame")
        if rig not in rigs:
            raise InputError(f"{where}: rig {rig!r} is not in the rig file (it has {', '.join(sorted(rigs))})")
        if sensor not in rigs[rig]:
            raise InputError(f"{where}: camera {sensor!r} is not a camera of rig {rig!r} (it has "
                             f"{', '.join(sorted(rigs[rig]))})")
        if (rig, frame, sensor) in slots:
            raise InputError(f"{where}: frame {frame!r} of rig {rig!r} has two images of camera {sensor!r} "
                             f"(first at {slots[rig, frame, sensor]})")
        named[name] = slots[rig, frame, sensor] = where
        members.setdefault((rig, frame), []).append((by_name[name], rigs[rig][sensor]))
    frames = [Frame(f"{rig}/{frame}", tuple(q for q, _ in m), tuple(C for _, C in m), {"rig": rig})
              for (rig, frame), m in members.items()]  # tagged: a body (an untagged frame is a query alone)
    frames += [Frame(q.name, (q,), (IDENTITY,)) for q in queries if q.name not in named]
    return frames



def read_odometry(path, queries: List[QueryRecord], chunk: int, listed_only: bool = False) -> List[Frame]:
    """The chunks of a sequence (see the module docstring): a ``Frame`` per ``chunk`` consecutive lines (the
    last may be shorter), then one frame of its own for each query that no line names. ``listed_only``: lines
    of images that are not among ``queries`` are passed over (a shard's part of a file read whole before)."""
    if chunk < 1:
        raise ValueError(f"--chunk {chunk}: a chunk has at least one frame")
    by_name = {q.name: q for q in queries}
    first: Dict[str, str] = {}
    sequence: List[Tuple[QueryRecord, np.ndarray]] = []
    for where, fields in _lines(path, "odometry file"):
        name = fields[0]
        pose = pose_from_line(fields[1:], where)
        if name in first:
            raise InputError(f"{where}: {name!r} is given twice (first at {first[name]})")
        first[name] = where
        if name not in by_name:
            if listed_only:
                continue
            raise InputError(f"{where}: {name!r} is not a query of the list")
        sequence.append((by_name[name], pose))
    frames = []
    for k in range(0, len(sequence), chunk):
        part = sequence[k:k + chunk]
        first_from_odom = invert(part[0][1])
        cams = tuple(compose(T, first_from_odom) for _, T in part)
        frames.append(Frame(f"chunk:{part[0][0].name}", tuple(q for q, _ in part), cams, {"sequence": "odometry"}))
    frames += [Frame(q.name, (q,), (IDENTITY,)) for q in queries if q.name not in first]
    return frames


def bodies_of(job, queries: List[QueryRecord], listed_only: bool = False) -> List[Frame]:
    """The frames a job localizes as bodies: its rig frames (``job.rigs``, ``job.rig_frames``) or its sequence's
    chunks (``job.odometry``, ``job.chunk``), each query of none alone; none where the job has neither."""
    if job.rigs is not None:
        return read_frames(job.rig_frames, queries, read_rigs(job.rigs), listed_only)
    if job.odometry is not None:
        return read_odometry(job.odometry, queries, job.chunk, listed_only)
    return []
