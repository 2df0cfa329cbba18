"""One reader for each text file a user hands us, or that we wrote and may find damaged.

Every error names its file and, for line formats, its line: ``path:line: what is wrong``
(``InputError``). Poses files (priors, ground truth) are strict: eight fields, finite numbers, a
quaternion that is not zero, one pose per name. Names are matched by their full relative path;
a name written with fewer folders (a bare file name, or ``camera/file``) matches a query whose
path ends with it, only where that is unambiguous (``PoseTable.find``).
"""

import functools
import json
import logging
import os
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Tuple

import numpy as np

logger = logging.getLogger(__name__)


class InputError(ValueError):
    """A file that cannot be read as what it should be; the message starts with the file (and line)."""


def read_text(path, what: str) -> str:
    """The text of ``path`` (UTF-8), or InputError naming it and ``what`` it should be."""
    path = Path(path)
    if not path.is_file():
        kind = "does not exist" if not path.exists() else (
            "does not exist (it is a folder)" if path.is_dir() else "is not a regular file (a device, FIFO or socket)")
        raise InputError(f"{path}: {what} {kind}")
    try:
        # utf-8-sig: a byte-order mark (what Notepad writes first) is not part of the first line
        return path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as e:
        raise InputError(f"{path}: {what} is not UTF-8 text (byte {e.start})") from None
    except OSError as e:
        raise InputError(f"{path}: {what} cannot be read: {e.strerror or e}") from None


def data_lines(path, what: str) -> Iterator[Tuple[int, List[str]]]:
    """(line number, whitespace-separated fields) of every line that is not blank or a ``#`` comment."""
    for line_no, line in enumerate(read_text(path, what).splitlines(), 1):
        if line.strip() and not line.lstrip().startswith("#"):
            yield line_no, line.split()


class _DuplicateKey(ValueError):
    pass


def _unique_keys(pairs):
    out = {}
    for key, value in pairs:
        if key in out:
            raise _DuplicateKey(key)
        out[key] = value
    return out


def read_json(path, what: str, kind: type = dict):
    """The JSON value of ``path``, of type ``kind``; InputError naming the file otherwise."""
    text = read_text(path, what)
    try:
        value = json.loads(text, object_pairs_hook=_unique_keys)
    except json.JSONDecodeError as e:
        raise InputError(f"{path}:{e.lineno}: {what} is not valid JSON ({e.msg}); it may be truncated") from None
    except _DuplicateKey as e:  # json keeps the last silently: one of two shots, frames or cameras lost
        raise InputError(f"{path}: {what} has the key {e.args[0]!r} twice in one object: each once") from None
    if not isinstance(value, kind):
        raise InputError(f"{path}: {what} should hold a JSON {kind.__name__}, not a {type(value).__name__}")
    return value


def read_yaml(path, what: str, kind: type = dict):
    """The YAML value of ``path`` (an empty file: an empty ``kind``), of type ``kind``; InputError
    naming the file (and line) otherwise."""
    import yaml

    text = read_text(path, what)
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark is not None else f"{path}"
        raise InputError(f"{where}: {what} is not valid YAML ({getattr(e, 'problem', None) or e})") from None
    value = kind() if value is None else value
    if not isinstance(value, kind):
        raise InputError(f"{path}: {what} should hold a YAML {'mapping' if kind is dict else kind.__name__}, "
                         f"not a {type(value).__name__}")
    return value


def _numbers(fields: List[str], where: str) -> np.ndarray:
    try:
        values = np.array([float(v) for v in fields], np.float64)
    except ValueError:
        raise InputError(f"{where}: expected numbers, got {' '.join(fields)!r}") from None
    if not np.isfinite(values).all():
        raise InputError(f"{where}: non-finite number in {' '.join(fields)!r}")
    return values


def pose_from_line(fields: List[str], where: str) -> np.ndarray:
    """cam_from_world (3, 4) from ``qw qx qy qz tx ty tz``; refuses a zero or non-finite quaternion."""
    from pipeline.scene import qvec_to_rotmat

    if len(fields) != 7:
        raise InputError(f"{where}: expected 'name qw qx qy qz tx ty tz' (8 fields), got {len(fields) + 1}")
    v = _numbers(fields, where)
    norm = float(np.linalg.norm(v[:4]))
    if norm < 1e-6:
        raise InputError(f"{where}: the quaternion {v[:4].tolist()} is zero: it is no rotation")
    if abs(norm - 1) > 1e-2:
        logger.warning("%s: quaternion of norm %.4f normalised", where, norm)
    return np.concatenate([qvec_to_rotmat(v[:4]), v[4:7, None]], 1)


class NameIndex:
    """Matches query names to the names a file gives (``match``)."""

    def __init__(self, names, path: str = ""):
        self.path = str(path)
        self._keys = {_parts(name): name for name in names}
        self._by_base: Dict[str, List[Tuple[str, ...]]] = {}
        for parts in self._keys:
            if parts:
                self._by_base.setdefault(parts[-1], []).append(parts)

    def match(self, name: str) -> Optional[str]:
        """The key of ``name``: the same relative path; else the one key that is a shorter ending of
        it (``frame.jpg`` or ``seq-01/frame.jpg`` for ``stairs/seq-01/frame.jpg``), or that it is an
        ending of. A key in another folder (``seq-04/frame.jpg``) never matches; two that fit
        match neither (logged)."""
        parts = _parts(name)
        if parts in self._keys:
            return self._keys[parts]
        if not parts:
            return None
        n = len(parts)
        found = [self._keys[k] for k in self._by_base.get(parts[-1], [])
                 if k == parts[-len(k):] or parts == k[-n:]]  # one ends the other, folder by folder
        if len(found) == 1:
            return found[0]
        if len(found) > 1:
            logger.warning("%s: %d entries of %s match this name (%s): none used", name, len(found),
                           self.path or "the file", ", ".join(found[:3]))
        return None


def find_by_name(mapping: Dict, name: str, index: Optional[NameIndex] = None):
    """``mapping``'s value for query ``name`` (``NameIndex.match``), or None."""
    key = (index or NameIndex(mapping)).match(name)
    return None if key is None else mapping[key]


class PoseTable:
    """Poses by name, as read from a poses file (``read_poses``); ``find`` gives a query's pose."""

    def __init__(self, poses: Dict[str, np.ndarray], path: str = ""):
        self.poses = poses
        self.path = str(path)
        self.index = NameIndex(poses, path)

    def __len__(self) -> int:
        return len(self.poses)

    def match(self, name: str) -> Optional[str]:
        return self.index.match(name)

    def find(self, name: str) -> Optional[np.ndarray]:
        return find_by_name(self.poses, name, self.index)


def _parts(name: str) -> Tuple[str, ...]:
    return tuple(p for p in name.replace("\\", "/").split("/") if p not in ("", "."))


def read_poses(path) -> PoseTable:
    """A poses file (``name qw qx qy qz tx ty tz`` per line, cam_from_world): priors or ground
    truth. A line that is short, long, not numeric, non-finite or with a zero quaternion, and a
    name given twice, is refused with ``file:line``."""
    path = str(path)
    poses: Dict[str, np.ndarray] = {}
    first: Dict[str, int] = {}
    for line_no, (name, *fields) in data_lines(path, "poses file"):
        where = f"{path}:{line_no}"
        if name in poses:
            raise InputError(f"{where}: {name} already has a pose (line {first[name]}): one pose per name")
        poses[name] = pose_from_line(fields, where)
        first[name] = line_no
    return PoseTable(poses, path)


@functools.lru_cache(maxsize=4)
def poses_file(path: str) -> PoseTable:
    """A poses file (priors), read once per process (``read_poses``)."""
    return read_poses(path)


def warn_partial_matches(table: PoseTable, names: List[str], what: str) -> None:
    """Log once how many of ``names`` were matched by a shorter name than their own."""
    loose = [n for n in names if (k := table.match(n)) is not None and k != n]
    if loose:
        logger.warning("%d queries matched in %s by a shorter name (e.g. %s -> %s): %s", len(loose), table.path,
                       loose[0], table.match(loose[0]), what)


def read_pairs(path) -> Dict[str, List[str]]:
    """Retrieval pairs ``query reference`` per line, kept in ranked order; a line with other than
    two fields is refused with ``file:line``."""
    pairs: Dict[str, List[str]] = {}
    for line_no, fields in data_lines(path, "pairs file"):
        if len(fields) != 2:
            raise InputError(f"{path}:{line_no}: expected 'query reference', got {len(fields)} fields "
                             "(names with spaces cannot be written in this format)")
        pairs.setdefault(fields[0], []).append(fields[1])
    return pairs



def write_atomic(path, data) -> None:
    """Write ``data`` (str or bytes) to ``path`` through a temporary file in the same folder, then
    rename: a reader sees the old file or the new one, never a part (a full disk, a kill). The
    temporary is removed when anything fails. A file that already holds these bytes is not
    written again."""
    path = Path(path)
    data = data.encode() if isinstance(data, str) else data
    try:
        if path.stat().st_size == len(data) and path.read_bytes() == data:
            return  # the same bytes: left untouched (a no-op rerun keeps its outputs' times)
    except OSError:
        pass
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def read_json_lines(path, what: str, key: str = "name") -> List[Dict]:
    """JSON objects, one per line, each with ``key``; InputError with ``file:line`` otherwise
    (a truncated or foreign file)."""
    out = []
    for line_no, line in enumerate(read_text(path, what).splitlines(), 1):
        if not line.strip():
            continue
        try:
            value = json.loads(line)
        except json.JSONDecodeError as e:
            raise InputError(f"{path}:{line_no}: {what}: not a JSON record ({e.msg}); the file is damaged") from None
        if not isinstance(value, dict) or key not in value:
            raise InputError(f"{path}:{line_no}: {what}: a record without {key!r}; the file is damaged or foreign")
        out.append(value)
    return out
