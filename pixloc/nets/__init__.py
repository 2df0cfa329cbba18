"""Networks: the PixLoc UNet (VGG or EfficientNet-Lite0 encoder) and checkpoint loading."""

from .efficientnet import lite0_unet
from .registry import CheckpointError, load_official_checkpoint, read_checkpoint
from .unet import UNet, vgg_unet

__all__ = ["CheckpointError", "UNet", "lite0_unet", "load_official_checkpoint", "read_checkpoint", "vgg_unet"]
