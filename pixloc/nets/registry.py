"""Feature models by name or file, the project's model file format, and a digest that
identifies a network's weights.

Names: ``pixloc-lite0`` (the model trained by this project, shipped in the package),
``lite0-imagenet`` (its untrained initialisation: ImageNet encoder, seeded random
decoder), ``photometric`` (raw RGB, no learning). Files: a model saved by
``save_model`` (``pixloc train`` exports one) or an official PixLoc checkpoint.
"""

import hashlib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Callable, Dict, Optional

import torch
from torch import nn

from .checkpoint import CheckpointError, load_official_checkpoint, read_checkpoint
from .efficientnet import lite0_unet
from .photometric import PhotometricExtractor
from ..optim import LearnedDamping, LevenbergMarquardt
from ..refiner import TwoViewRefiner

MODEL_FORMAT = "pixloc-at-scale-model"
DEFAULT_MODEL = "pixloc-lite0"  # the one default of every command and config


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


def _refiner(net: nn.Module, normalize_features: bool = True) -> TwoViewRefiner:
    """The network with the official initial damping (LearnedDamping at theta = 0) per level."""
    solvers = [LevenbergMarquardt(LearnedDamping(), num_iters=100, pad=2) for _ in net.strides]
    return TwoViewRefiner(net, solvers, normalize_features=normalize_features).eval()


def available_models() -> Dict[str, str]:
    """Name -> what it is."""
    return {name: m.description for name, m in NAMED.items()}


def shipped_model_path(name: str) -> Path:
    return Path(str(resources.files(__package__) / "weights" / NAMED[name].weights))


def load_refiner(spec: str) -> TwoViewRefiner:
    """A model by name, or from a file saved by ``save_model`` or an official checkpoint."""
    named = NAMED.get(spec)
    if named is not None and named.build is not None:
        return _refiner(named.build().eval(), normalize_features=named.normalize_features)
    if named is not None:
        path = shipped_model_path(spec)
        if not path.is_file():
            raise CheckpointError(f"The package has no weights for {spec!r} ({path} is missing).")
        return load_model(path)
    if Path(spec).is_file():
        ckpt = read_checkpoint(spec)
        return _from_model_dict(ckpt, spec) if ckpt.get("format") == MODEL_FORMAT else load_official_checkpoint(spec)
    raise ValueError(f"Unknown feature model {spec!r}: give one of {sorted(available_models())} or a model file.")


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
    return _from_model_dict(read_checkpoint(path), path)


def model_info(spec: str) -> Dict[str, Any]:
    """The ``info`` dict of a model file or shipped model ({} for other models)."""
    path = shipped_model_path(spec) if NAMED.get(spec, Named("")).weights else Path(spec)
    if not path.is_file():
        return {}
    ckpt = read_checkpoint(path)
    return dict(ckpt.get("info", {})) if ckpt.get("format") == MODEL_FORMAT else {}


def _from_model_dict(ckpt: Dict[str, Any], path) -> TwoViewRefiner:
    if ckpt.get("version") != 1 or ckpt.get("architecture") not in ARCHITECTURES:
        raise CheckpointError(f"{path}: unsupported model file (version {ckpt.get('version')}, "
                              f"architecture {ckpt.get('architecture')!r}).")
    refiner = _refiner(ARCHITECTURES[ckpt["architecture"]](), bool(ckpt.get("normalize_features", True)))
    state = {k: v.float() if v.is_floating_point() else v for k, v in ckpt["state"].items()}
    try:
        refiner.load_state_dict(state, strict=True)
    except RuntimeError as e:
        raise CheckpointError(f"{path}: weights do not fit the {ckpt['architecture']} network: {e}") from None
    return refiner.eval()


def state_digest(module: nn.Module) -> str:
    """SHA-256 (first 16 hex digits) of a module's parameters and buffers, by name."""
    h = hashlib.sha256()
    for name, tensor in sorted(module.state_dict().items()):
        h.update(name.encode())
        h.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]
