"""Networks: the PixLoc UNet (VGG or EfficientNet-Lite0 encoder) and checkpoint loading."""

from .checkpoint import CheckpointError, load_official_checkpoint, read_checkpoint
from .efficientnet import lite0_unet
from .unet import UNet, vgg_unet

__all__ = ["CheckpointError", "UNet", "lite0_unet", "load_official_checkpoint", "read_checkpoint", "vgg_unet"]
