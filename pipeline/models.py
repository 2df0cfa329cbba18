"""The model a process works with, loaded once: the refiner (feature network and its per-level
solvers; the network prepared for inference, ``prepare_for_inference``) and its network's
digest. Map building takes its network, localization all of it; a process that does both holds
one copy."""

import functools
from typing import Tuple

from torch import nn

from pixloc.nets.registry import load_refiner
from pixloc.nets.unet import prepare_for_inference
from pixloc.refiner import TwoViewRefiner


def localization_model(model: str, device: str = "cpu") -> Tuple[TwoViewRefiner, str]:
    """The refiner of ``model`` (a name or a file, ``pixloc.nets.registry.load_refiner``) on
    ``device``, in eval mode, and its network's digest (what a store records of its features)."""
    return _loaded(model, device)  # one cache key however the device is passed


@functools.lru_cache(maxsize=2)
def _loaded(model: str, device: str) -> Tuple[TwoViewRefiner, str]:
    refiner = load_refiner(model).to(device).eval()
    digest = refiner.feature_digest()  # of the weights as trained, before folding
    prepare_for_inference(refiner.extractor, device)
    return refiner, digest


def network(model: str, device: str = "cpu") -> Tuple[nn.Module, str]:
    """The feature network of ``localization_model`` and its digest."""
    refiner, digest = localization_model(model, device)
    return refiner.extractor, digest

