"""Pickles of other tools (official PixLoc info files, hloc logs), read as data only.

A pickle can name any callable, and loading it runs that callable. These files come from
elsewhere, so they are read with an unpickler that accepts plain containers, numpy arrays and
the few data classes a caller allows (pycolmap poses), and refuses everything else.
"""

import pickle
from pathlib import Path
from typing import Any, FrozenSet, Tuple

from pipeline.scene import SceneError

_NUMPY = frozenset({
    ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
    ("numpy", "ndarray"), ("numpy", "dtype"), ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "scalar"), ("collections", "OrderedDict"), ("collections", "defaultdict"),
    ("builtins", "set"), ("builtins", "frozenset"), ("builtins", "list"), ("builtins", "dict")})


class _DataUnpickler(pickle.Unpickler):
    allowed: FrozenSet[Tuple[str, str]] = _NUMPY

    def find_class(self, module, name):
        if (module, name) in self.allowed or (module == "numpy.dtypes" and name.endswith("DType")):
            return super().find_class(module, name)
        raise SceneError(f"Refusing to load {module}.{name} from a pickle: only data is allowed.")


def load_data_pickle(path, what: str, allowed: FrozenSet[Tuple[str, str]] = frozenset()) -> Any:
    """The object in pickle ``path``; ``what`` names the expected file in errors; ``allowed``
    adds (module, name) classes to numpy's."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{what} {path} does not exist.")
    unpickler = type("_Unpickler", (_DataUnpickler,), {"allowed": _NUMPY | frozenset(allowed)})
    with open(path, "rb") as f:
        try:
            return unpickler(f).load()
        except SceneError:  # a class that is not data
            raise
        except Exception as e:  # damaged bytes fail the unpickler in any way: KeyError, IndexError, MemoryError...
            raise SceneError(f"{path} is not a readable {what}: {type(e).__name__}: {e}") from None
