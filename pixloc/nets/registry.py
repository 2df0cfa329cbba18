"""Feature networks by name or checkpoint path, and a digest that identifies their weights."""

import hashlib
from pathlib import Path
from typing import Callable, Dict

import torch
from torch import nn

from .checkpoint import load_official_checkpoint
from .efficientnet import lite0_unet
from ..optim import LearnedDamping, LevenbergMarquardt
from ..refiner import TwoViewRefiner
from .unet import UNet


def _seeded(build: Callable[[], UNet], seed: int = 0) -> Callable[[], UNet]:
    def fn() -> UNet:
        with torch.random.fork_rng():
            torch.manual_seed(seed)  # the randomly initialised decoder is reproducible
            return build()
    return fn


MODELS: Dict[str, Callable[[], UNet]] = {
    "lite0-imagenet": _seeded(lambda: lite0_unet(pretrained=True)),
}


def load_refiner(spec: str) -> TwoViewRefiner:
    """Network and per-level LM solvers: an official checkpoint's, or a named network with
    the official initial damping (LearnedDamping at theta = 0) on every level."""
    if spec in MODELS:
        net = MODELS[spec]().eval()
        solvers = [LevenbergMarquardt(LearnedDamping(), num_iters=100, pad=2) for _ in net.strides]
        return TwoViewRefiner(net, solvers).eval()
    if Path(spec).is_file():
        return load_official_checkpoint(spec)
    raise ValueError(f"Unknown feature model {spec!r}: give one of {sorted(MODELS)} or a checkpoint file.")


def load_extractor(spec: str) -> UNet:
    """The feature network of ``load_refiner(spec)``, in eval mode."""
    return load_refiner(spec).extractor.eval()


def state_digest(module: nn.Module) -> str:
    """SHA-256 (first 16 hex digits) of a module's parameters and buffers, by name."""
    h = hashlib.sha256()
    for name, tensor in sorted(module.state_dict().items()):
        h.update(name.encode())
        h.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]
