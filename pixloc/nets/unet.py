"""The PixLoc UNet: multilevel features and confidences, in the official layout.

Sarlin et al. 2021, Sec. 3.1 and cvg/pixloc ``pixlib/models/unet.py``: an
encoder split at its pooling layers, a decoder of (bilinear x2 upsample, crop
the skip, concat, 3x3 conv + BatchNorm + ReLU) blocks, and 1x1 "adaptation"
convs to the output levels, plus a 1x1 conv per level for the confidence
``sigmoid(-u)``. Module names match official checkpoints, so their state
dicts load strictly.
"""

from typing import Dict, List, Sequence

import torch
import torch.utils.checkpoint
from torch import Tensor, nn

# torchvision's VGG configurations: conv widths, "M" = 2x2 max-pool.
VGG_LAYERS = {
    "vgg16": [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M",
              512, 512, 512, "M"],
    "vgg19": [64, 64, "M", 128, 128, "M", 256, 256, 256, 256, "M", 512, 512, 512, 512, "M",
              512, 512, 512, 512, "M"],
}
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def vgg_blocks(name: str, num_downsample: int = 4):
    """VGG feature layers split at the max-pools into num_downsample + 1 blocks.

    Layer indices inside each block follow torchvision's ``features`` list, so
    that official state-dict keys (``encoder.{block}.{index}``) match. Returns
    the blocks and the channel count at the end of each (the skip dims).
    """
    if name not in VGG_LAYERS:
        raise ValueError(f"Unknown VGG encoder {name!r}; known: {sorted(VGG_LAYERS)}.")
    blocks: List[List[nn.Module]] = [[]]
    skip_dims, channels = [], 3
    for v in VGG_LAYERS[name]:
        if v == "M":
            skip_dims.append(channels)
            if len(blocks) == num_downsample + 1:
                break
            blocks.append([nn.MaxPool2d(kernel_size=2, stride=2)])
        else:
            blocks[-1] += [nn.Conv2d(channels, v, kernel_size=3, padding=1), nn.ReLU(inplace=True)]
            channels = v
    return nn.ModuleList(nn.Sequential(*b) for b in blocks), skip_dims


class DecoderBlock(nn.Module):
    """Upsample x2 (bilinear), crop the skip to match (floor-mode pooling), concat, conv."""

    def __init__(self, previous: int, skip: int, out: int):
        super().__init__()
        self.layers = nn.Sequential(
            nn.Conv2d(previous + skip, out, kernel_size=3, padding=1, bias=False),
            nn.BatchNorm2d(out), nn.ReLU(inplace=True))

    def forward(self, previous: Tensor, skip: Tensor) -> Tensor:
        up = nn.functional.interpolate(previous, scale_factor=2, mode="bilinear", align_corners=False)
        h, w = up.shape[-2:]
        return self.layers(torch.cat([up, skip[..., :h, :w]], 1))


def _direct(block: nn.Module, *args: Tensor) -> Tensor:
    return block(*args)


def _checkpointed(block: nn.Module, *args: Tensor) -> Tensor:
    return torch.utils.checkpoint.checkpoint(block, *args, use_reentrant=False)


class UNet(nn.Module):
    """Feature pyramid network of PixLoc.

    encoder: ModuleList of blocks applied in sequence; block k outputs the
        skip at stride 2^k (block 0 at stride 1).
    skip_dims: channels of each block's output.
    decoder: channels of the decoder blocks, coarse to fine (official [64, 64, 64, 32]).
    output_scales: log2 strides of the output levels (official [0, 2, 4]).
    output_dims: channels of each output level (official [32, 128, 128]).
    mean, std: input normalisation of the encoder.
    crop_input: crop images to a multiple of the coarsest stride before the
        encoder, for encoders with strided convs (ceil-mode sizes); VGG's
        floor-mode pooling crops by itself.

    forward(image (B, 3, H, W) RGB in [0, 1]) returns ``features``, a list of
    (B, C_l, H_l, W_l) maps, finest first, before L2 normalisation, and
    ``confidences``, a list of (B, 1, H_l, W_l) maps in (0, 1).
    """

    def __init__(self, encoder: nn.ModuleList, skip_dims: Sequence[int],
                 decoder: Sequence[int] = (64, 64, 64, 32), output_scales: Sequence[int] = (0, 2, 4),
                 output_dims: Sequence[int] = (32, 128, 128), compute_confidence: bool = True,
                 mean: Sequence[float] = IMAGENET_MEAN, std: Sequence[float] = IMAGENET_STD,
                 crop_input: bool = False):
        super().__init__()
        self.crop_input = crop_input
        if len(decoder) != len(skip_dims) - 1:
            raise ValueError(f"The decoder needs {len(skip_dims) - 1} blocks, got {len(decoder)}.")
        if len(output_dims) != len(output_scales) or max(output_scales) >= len(skip_dims):
            raise ValueError(f"Bad output levels: scales {output_scales}, dims {output_dims}.")
        self.encoder = encoder
        blocks, previous = [], skip_dims[-1]
        for out, skip in zip(decoder, skip_dims[:-1][::-1]):
            blocks.append(DecoderBlock(previous, skip, out))
            previous = out
        self.decoder = nn.ModuleList(blocks)
        # The coarsest level adapts the encoder's last map (no decoder block there).
        in_dims = [skip_dims[i] if i == len(skip_dims) - 1 else decoder[-1 - i] for i in output_scales]
        self.adaptation = nn.ModuleList(
            nn.Sequential(nn.Conv2d(i, o, kernel_size=1)) for i, o in zip(in_dims, output_dims))
        if compute_confidence:
            self.uncertainty = nn.ModuleList(
                nn.Sequential(nn.Conv2d(i, 1, kernel_size=1)) for i in in_dims)
        self.output_scales = tuple(output_scales)
        self.strides = tuple(2 ** s for s in output_scales)
        self.output_dims = tuple(output_dims)
        self.grad_checkpointing = False  # recompute block activations in backward (less memory)
        self.register_buffer("mean", torch.tensor(mean).view(3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(std).view(3, 1, 1), persistent=False)

    @property
    def compute_confidence(self) -> bool:
        return hasattr(self, "uncertainty")

    def forward(self, image: Tensor) -> Dict[str, List[Tensor]]:
        if image.dim() != 4 or image.shape[1] != 3:
            raise ValueError(f"Expected images (B, 3, H, W), got {tuple(image.shape)}.")
        min_size = 2 ** (len(self.encoder) - 1)
        if min(image.shape[-2:]) < min_size:
            raise ValueError(f"Images must be at least {min_size} px on each side, got {tuple(image.shape[-2:])}.")
        if self.crop_input:
            h, w = (s - s % min_size for s in image.shape[-2:])
            image = image[..., :h, :w]
        x = (image - self.mean) / self.std
        run = _checkpointed if self.grad_checkpointing and torch.is_grad_enabled() else _direct
        skips = []
        for block in self.encoder:
            x = run(block, x)
            skips.append(x)
        pre = [skips[-1]]
        for block, skip in zip(self.decoder, skips[:-1][::-1]):
            pre.append(run(block, pre[-1], skip))
        pre = pre[::-1]  # fine to coarse, index = log2 stride
        out = {"features": [adapt(pre[i]) for adapt, i in zip(self.adaptation, self.output_scales)]}
        if self.compute_confidence:
            out["confidences"] = [torch.sigmoid(-unc(pre[i]))
                                  for unc, i in zip(self.uncertainty, self.output_scales)]
        return out


def vgg_unet(encoder: str = "vgg19", **kwargs) -> UNet:
    """The official PixLoc network with a VGG encoder (random init; load a checkpoint)."""
    blocks, skip_dims = vgg_blocks(encoder)
    return UNet(blocks, skip_dims, **kwargs)
