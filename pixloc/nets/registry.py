"""Feature models by name or file: the names this project knows, its model file format, official
PixLoc checkpoints (``checkpoint_best.tar``), each read into a ``Recipe`` and built in one place.

Names: ``pixloc-lite0`` (the model trained by this project, shipped in the package),
``lite0-imagenet`` (its untrained initialisation: ImageNet encoder, seeded random
decoder), ``photometric`` (raw RGB, no learning). Files: a model saved by
``save_model`` (``pixloc train`` exports one) or an official PixLoc checkpoint.

Every file is read with ``torch.load(weights_only=True)``: only tensors, plain containers and
the numpy scalar types that official checkpoints store in ``eval`` are allowed. Anything needing
arbitrary pickled code is refused.
"""

import functools
import pickle
import zipfile
import zlib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Callable, Dict, Optional

import numpy as np
import torch
from torch import nn

from .efficientnet import lite0_unet
from .photometric import PhotometricExtractor
from .unet import VGG_LAYERS, vgg_unet
from .. import DEFAULT_MODEL  # noqa: F401 (imported from here)
from ..optim import LearnedDamping, LevenbergMarquardt
from ..refiner import TwoViewRefiner

MODEL_FORMAT = "pixloc-at-scale-model"


def _seeded(build: Callable[[], nn.Module], seed: int = 0) -> Callable[[], nn.Module]:
    def fn() -> nn.Module:
        with torch.random.fork_rng():
            torch.manual_seed(seed)  # the randomly initialised decoder is reproducible
            return build()
    return fn


ARCHITECTURES: Dict[str, Callable[[], nn.Module]] = {
    "lite0": lambda: lite0_unet(pretrained=False),
    "photometric": PhotometricExtractor,
}


@dataclass(frozen=True)
class Named:
    """A model known by name: what it is, and either the file of its weights in
    pixloc/nets/weights (shipped) or the function that builds its network."""

    description: str
    weights: Optional[str] = None
    build: Optional[Callable[[], nn.Module]] = None
    normalize_features: bool = True


# every model known by name, in one table (what the commands list and accept)
NAMED: Dict[str, Named] = {
    "pixloc-lite0": Named("trained by this project (shipped)", weights="pixloc-lite0.pt"),
    "lite0-imagenet": Named("untrained initialisation", build=_seeded(lambda: lite0_unet(pretrained=True))),
    "photometric": Named("raw RGB features (baseline)", build=PhotometricExtractor, normalize_features=False),
}


def _initial_solver() -> LevenbergMarquardt:
    """The official initial damping (LearnedDamping at theta = 0)."""
    return LevenbergMarquardt(LearnedDamping(), num_iters=100, pad=2)


@dataclass
class Recipe:
    """What a model is made of, read and checked before anything is built: its network's
    constructor, one solver per level, the refiner's options and, for a file, its weights."""

    source: str  # the name or file, for messages
    network: Callable[[], nn.Module]
    solver: Callable[[], LevenbergMarquardt] = _initial_solver
    options: Dict[str, Any] = field(default_factory=dict)  # TwoViewRefiner's keyword arguments
    state: Optional[Dict[str, torch.Tensor]] = None


def available_models() -> Dict[str, str]:
    """Name -> what it is."""
    return {name: m.description for name, m in NAMED.items()}


def shipped_model_path(name: str) -> Path:
    return Path(str(resources.files(__package__) / "weights" / NAMED[name].weights))


def model_recipe(spec: str) -> Recipe:
    """The recipe of a model by name, or of a file saved by ``save_model`` or an official checkpoint."""
    named = NAMED.get(spec)
    if named is not None and named.build is not None:
        return Recipe(spec, named.build, options={"normalize_features": named.normalize_features})
    if named is not None:
        path = shipped_model_path(spec)
        if not path.is_file():
            raise CheckpointError(f"The package has no weights for {spec!r} ({path} is missing).")
        return model_file_recipe(read_checkpoint(path), path)
    if Path(spec).is_file():
        ckpt = read_checkpoint(spec)
        return model_file_recipe(ckpt, spec) if ckpt.get("format") == MODEL_FORMAT else official_recipe(ckpt, spec)
    raise ValueError(f"Unknown feature model {spec!r}: give one of {sorted(available_models())} or a model file.")


def load_refiner(spec: str) -> TwoViewRefiner:
    """A model (in eval mode) by name, or from a file saved by ``save_model`` or an official checkpoint."""
    recipe = model_recipe(spec)
    return build_refiner(recipe)


def build_refiner(recipe: Recipe) -> TwoViewRefiner:
    """The refiner (in eval mode) that a recipe describes: the one place where one is built."""
    net = recipe.network().eval()
    refiner = TwoViewRefiner(net, [recipe.solver() for _ in net.strides], **recipe.options)
    if recipe.state is not None:
        try:
            missing, unexpected = refiner.load_state_dict(recipe.state, strict=False)
        except RuntimeError as e:  # a tensor of another shape
            raise CheckpointError(f"{recipe.source} does not match its configuration: {e}") from None
        if missing or unexpected:
            raise CheckpointError(f"{recipe.source} does not match its configuration: missing {missing[:5]}, "
                                  f"unexpected {unexpected[:5]}.")
        broken = [k for k, v in recipe.state.items() if v.is_floating_point() and not torch.isfinite(v).all()]
        if broken:
            raise CheckpointError(f"{recipe.source} holds weights that are not finite numbers: {broken[:3]}.")
    return refiner.eval()


def save_model(refiner: TwoViewRefiner, architecture: str, path, info: Optional[Dict[str, Any]] = None,
               half: bool = True) -> Path:
    """Write ``refiner`` in the project's model format: network weights (float16 if
    ``half``; BatchNorm statistics and damping stay float32) and an ``info`` dict."""
    if architecture not in ARCHITECTURES:
        raise ValueError(f"Unknown architecture {architecture!r}; known: {sorted(ARCHITECTURES)}.")
    state = {}
    for k, v in refiner.state_dict().items():
        v = v.detach().cpu()
        if half and v.is_floating_point() and k.startswith("extractor.") and "running_" not in k:
            v = v.half()
        state[k] = v.clone()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save({"format": MODEL_FORMAT, "version": 1, "architecture": architecture,
                "normalize_features": refiner.normalize_features, "state": state, "info": info or {}}, tmp)
    tmp.replace(path)
    return path


def load_model(path) -> TwoViewRefiner:
    return load_refiner(str(path))


def model_info(spec: str) -> Dict[str, Any]:
    """The ``info`` dict of a model file or shipped model ({} for other models)."""
    path = shipped_model_path(spec) if NAMED.get(spec, Named("")).weights else Path(spec)
    if not path.is_file():
        return {}
    ckpt = read_checkpoint(path)
    return dict(ckpt.get("info", {})) if ckpt.get("format") == MODEL_FORMAT else {}


def model_file_recipe(ckpt: Dict[str, Any], path) -> Recipe:
    """The recipe of a file saved by ``save_model`` (float16 weights are read back as float32)."""
    if ckpt.get("version") != 1 or ckpt.get("architecture") not in ARCHITECTURES:
        raise CheckpointError(f"{path}: unsupported model file (version {ckpt.get('version')}, "
                              f"architecture {ckpt.get('architecture')!r}).")
    state = {k: v.float() if v.is_floating_point() else v for k, v in ckpt["state"].items()}
    return Recipe(f"{path} ({ckpt['architecture']})", ARCHITECTURES[ckpt["architecture"]],
                  options={"normalize_features": bool(ckpt.get("normalize_features", True))}, state=state)


# --- official PixLoc checkpoints ---------------------------------------------------------------

class CheckpointError(ValueError):
    """A checkpoint that is corrupt, unsafe, or not an official PixLoc one."""


def _numpy_safe_globals():
    scalar = np._core.multiarray.scalar if hasattr(np, "_core") else np.core.multiarray.scalar
    allowed = [scalar, (scalar, "numpy.core.multiarray.scalar"), np.dtype]
    for name in ("Float64DType", "Float32DType", "Int64DType", "Int32DType", "BoolDType"):
        if hasattr(np, "dtypes") and hasattr(np.dtypes, name):
            allowed.append(getattr(np.dtypes, name))
    return allowed


def _check_zip(path: Path) -> None:
    """A checkpoint in PyTorch's zip format (every one saved since torch 1.6) has a CRC-32 per record,
    which ``torch.load`` does not check: a damaged byte in a tensor would load as other weights."""
    if not zipfile.is_zipfile(path):
        return
    _check_zip_end(path)
    try:
        with zipfile.ZipFile(path) as archive:
            bad = archive.testzip()
    except (zipfile.BadZipFile, OSError, ValueError, EOFError, NotImplementedError, zlib.error, RuntimeError) as e:
        raise CheckpointError(f"{path} is corrupt or not a PyTorch checkpoint: {e}") from None
    if bad is not None:
        raise CheckpointError(f"{path} is corrupt: its record {bad} fails its checksum (the file was damaged "
                              "after it was written).")


def _check_zip_end(path: Path) -> None:
    """The zip's end record must end the file: its comment length, which no CRC covers, equals the bytes
    after it (a damaged length or a truncated comment is a damaged file, which zipfile and torch read)."""
    with open(path, "rb") as f:
        f.seek(0, 2)
        size = f.tell()
        f.seek(max(0, size - 22 - 65535))
        tail = f.read()
    at = tail.rfind(b"PK\x05\x06")
    if at < 0 or at + 22 > len(tail) or at + 22 + int.from_bytes(tail[at + 20:at + 22], "little") != len(tail):
        raise CheckpointError(f"{path} is corrupt: the end of its zip directory does not match the file's length "
                              "(the file was damaged after it was written).")


def read_checkpoint(path) -> Dict[str, Any]:
    """The checkpoint's dict, loaded without executing pickled code."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"Checkpoint {path} does not exist.")
    _check_zip(path)
    try:
        with torch.serialization.safe_globals(_numpy_safe_globals()):
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        raise CheckpointError(
            f"Refusing {path}: loading it would require running arbitrary pickled code, which is "
            f"not allowed for checkpoints ({str(e).splitlines()[-1] if str(e) else e}).") from None
    except Exception as e:  # damaged bytes fail torch's legacy unpickler in any way: KeyError, IndexError...
        raise CheckpointError(f"{path} is corrupt or not a PyTorch checkpoint: {type(e).__name__}: {e}") from None
    if not isinstance(ckpt, dict):
        raise CheckpointError(f"{path} is not a PixLoc checkpoint: it holds a {type(ckpt).__name__}.")
    return ckpt


def _get(conf: Dict, key: str, default=None):
    return conf.get(key, default) if isinstance(conf, dict) else default


def official_recipe(ckpt: Dict[str, Any], path) -> Recipe:
    """The recipe of an official ``checkpoint_best.tar``: its ``conf['model']`` and its weights,
    renamed to ours."""
    if not {"model", "conf"} <= set(ckpt) or not isinstance(ckpt["model"], dict):
        raise CheckpointError(f"{path} is not an official PixLoc checkpoint: expected the keys 'model' and "
                              f"'conf', found {sorted(map(str, ckpt))}.")
    conf = _get(ckpt["conf"], "model")
    if _get(conf, "name") != "two_view_refiner":
        raise CheckpointError(f"Unsupported model {_get(conf, 'name')!r}: expected 'two_view_refiner'.")
    ext = _get(conf, "extractor", {})
    if _get(ext, "name") != "unet" or _get(ext, "encoder") not in VGG_LAYERS:
        raise CheckpointError(f"Unsupported extractor {_get(ext, 'name')!r} with encoder "
                              f"{_get(ext, 'encoder')!r}: expected a unet on {sorted(VGG_LAYERS)}.")
    scales = list(_get(ext, "output_scales", [0, 2, 4]))
    dims = _get(ext, "output_dim", 128)
    dims = [dims] * len(scales) if isinstance(dims, int) else list(dims)
    network = functools.partial(vgg_unet, ext["encoder"], decoder=list(_get(ext, "decoder", [64, 64, 64, 64])),
                                output_scales=scales, output_dims=dims,
                                compute_confidence=bool(_get(ext, "compute_uncertainty", False)))
    opt = _get(conf, "optimizer", {})
    damping = _get(opt, "damping", {})
    if _get(opt, "name") != "learned_optimizer" or _get(damping, "type", "constant") != "constant":
        raise CheckpointError(f"Unsupported optimizer {_get(opt, 'name')!r}: expected a "
                              "learned_optimizer with constant damping.")
    interpolation = _get(opt, "interpolation", {})

    def solver() -> LevenbergMarquardt:  # a damping of its own per level
        return LevenbergMarquardt(LearnedDamping(tuple(_get(damping, "log_range", (-6, 5)))),
                                  loss=_get(opt, "loss_fn", "squared_loss"), num_iters=int(_get(opt, "num_iters", 100)),
                                  pad=int(_get(opt, "pad", _get(interpolation, "pad", 4))),
                                  interpolation=_get(interpolation, "mode", "linear"))
    options = {"normalize_features": bool(_get(conf, "normalize_features", True)),
               "success_thresh": float(_get(conf, "success_thresh", 2)),
               "clamp_error": float(_get(conf, "clamp_error", 50))}
    return Recipe(f"{path} (official)", network, solver, options,
                  convert_official_state_dict(ckpt["model"], len(scales)))


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
    recipe = official_recipe(read_checkpoint(path), path)
    return build_refiner(recipe)
