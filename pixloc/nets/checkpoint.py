"""Load official cvg/pixloc checkpoints (``checkpoint_best.tar``) safely.

The file is read with ``torch.load(weights_only=True)``: only tensors, plain
containers and the numpy scalar types that official checkpoints store in
``eval`` are allowed. Anything needing arbitrary pickled code is refused.
"""

import pickle
import zipfile
from pathlib import Path
from typing import Any, Dict

import numpy as np
import torch

from ..optim import LearnedDamping, LevenbergMarquardt
from ..refiner import TwoViewRefiner
from .unet import VGG_LAYERS, vgg_unet


class CheckpointError(ValueError):
    """A checkpoint that is corrupt, unsafe, or not an official PixLoc one."""


def _numpy_safe_globals():
    scalar = np._core.multiarray.scalar if hasattr(np, "_core") else np.core.multiarray.scalar
    allowed = [scalar, (scalar, "numpy.core.multiarray.scalar"), np.dtype]
    for name in ("Float64DType", "Float32DType", "Int64DType", "Int32DType", "BoolDType"):
        if hasattr(np, "dtypes") and hasattr(np.dtypes, name):
            allowed.append(getattr(np.dtypes, name))
    return allowed


def read_checkpoint(path) -> Dict[str, Any]:
    """The checkpoint's dict, loaded without executing pickled code."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"Checkpoint {path} does not exist.")
    try:
        with torch.serialization.safe_globals(_numpy_safe_globals()):
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        raise CheckpointError(
            f"Refusing {path}: loading it would require running arbitrary pickled code, which is "
            f"not allowed for checkpoints ({str(e).splitlines()[-1] if str(e) else e}).") from None
    except (RuntimeError, EOFError, zipfile.BadZipFile, OSError, ValueError) as e:
        raise CheckpointError(f"{path} is corrupt or not a PyTorch checkpoint: {e}") from None
    if not isinstance(ckpt, dict):
        raise CheckpointError(f"{path} is not a PixLoc checkpoint: it holds a {type(ckpt).__name__}.")
    return ckpt


def _get(conf: Dict, key: str, default=None):
    return conf.get(key, default) if isinstance(conf, dict) else default


def refiner_from_conf(conf: Dict[str, Any]) -> TwoViewRefiner:
    """Build a TwoViewRefiner from an official ``conf['model']`` dict."""
    if _get(conf, "name") != "two_view_refiner":
        raise CheckpointError(f"Unsupported model {_get(conf, 'name')!r}: expected 'two_view_refiner'.")
    ext = _get(conf, "extractor", {})
    if _get(ext, "name") != "unet" or _get(ext, "encoder") not in VGG_LAYERS:
        raise CheckpointError(f"Unsupported extractor {_get(ext, 'name')!r} with encoder "
                              f"{_get(ext, 'encoder')!r}: expected a unet on {sorted(VGG_LAYERS)}.")
    scales = list(_get(ext, "output_scales", [0, 2, 4]))
    dims = _get(ext, "output_dim", 128)
    dims = [dims] * len(scales) if isinstance(dims, int) else list(dims)
    extractor = vgg_unet(ext["encoder"], decoder=list(_get(ext, "decoder", [64, 64, 64, 64])),
                         output_scales=scales, output_dims=dims,
                         compute_confidence=bool(_get(ext, "compute_uncertainty", False)))
    opt = _get(conf, "optimizer", {})
    if _get(opt, "name") != "learned_optimizer" or _get(_get(opt, "damping", {}), "type", "constant") != "constant":
        raise CheckpointError(f"Unsupported optimizer {_get(opt, 'name')!r}: expected a "
                              "learned_optimizer with constant damping.")
    pad = _get(opt, "pad", _get(_get(opt, "interpolation", {}), "pad", 4))
    solvers = [LevenbergMarquardt(
        LearnedDamping(tuple(_get(_get(opt, "damping", {}), "log_range", (-6, 5)))),
        loss=_get(opt, "loss_fn", "squared_loss"), num_iters=int(_get(opt, "num_iters", 100)),
        pad=int(pad), interpolation=_get(_get(opt, "interpolation", {}), "mode", "linear"))
        for _ in scales]
    return TwoViewRefiner(extractor, solvers,
                          normalize_features=bool(_get(conf, "normalize_features", True)),
                          success_thresh=float(_get(conf, "success_thresh", 2)),
                          clamp_error=float(_get(conf, "clamp_error", 50)))


def convert_official_state_dict(state: Dict[str, torch.Tensor], num_levels: int) -> Dict[str, torch.Tensor]:
    """Official keys -> ours: ``optimizer.{l}.dampingnet.const`` -> ``solvers.{l}.damping.theta``.

    A single shared optimizer (``duplicate_optimizer_per_scale: false``) is
    copied to every level.
    """
    out = {}
    for key, value in state.items():
        if key.startswith("optimizer."):
            rest = key[len("optimizer."):]
            if rest == "dampingnet.const":
                for level in range(num_levels):
                    out[f"solvers.{level}.damping.theta"] = value
                continue
            level, _, name = rest.partition(".")
            if name != "dampingnet.const":
                raise CheckpointError(f"Unexpected optimizer parameter {key!r} in the checkpoint.")
            out[f"solvers.{level}.damping.theta"] = value
        else:
            out[key] = value
    return out


def load_official_checkpoint(path) -> TwoViewRefiner:
    """A TwoViewRefiner (in eval mode) from an official ``checkpoint_best.tar``."""
    ckpt = read_checkpoint(path)
    if not {"model", "conf"} <= set(ckpt) or not isinstance(ckpt["model"], dict):
        raise CheckpointError(f"{path} is not an official PixLoc checkpoint: expected the keys 'model' and "
                              f"'conf', found {sorted(map(str, ckpt))}.")
    model = refiner_from_conf(_get(ckpt["conf"], "model"))
    state = convert_official_state_dict(ckpt["model"], len(model.solvers))
    missing, unexpected = model.load_state_dict(state, strict=False)
    if missing or unexpected:
        raise CheckpointError(f"{path} does not match its configuration: missing {missing[:5]}, "
                              f"unexpected {unexpected[:5]}.")
    return model.eval()
