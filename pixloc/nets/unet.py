"""The PixLoc UNet: multilevel features and confidences, in the official layout.

Sarlin et al. 2021, Sec. 3.1 and cvg/pixloc ``pixlib/models/unet.py``: an
encoder split at its pooling layers, a decoder of (bilinear x2 upsample, crop
the skip, concat, 3x3 conv + BatchNorm + ReLU) blocks, and 1x1 "adaptation"
convs to the output levels, plus a 1x1 conv per level for the confidence
``sigmoid(-u)``. Module names match official checkpoints, so their state
dicts load strictly.
"""

import functools
from typing import Dict, List, Optional, Sequence, Tuple

import torch
import torch.utils.checkpoint
from torch import Tensor, nn
from torch.nn.utils.fusion import fuse_conv_bn_eval

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
        self.skip_channels, self.out_channels = skip, out
        self.layers = nn.Sequential(
            nn.Conv2d(previous + skip, out, kernel_size=3, padding=1, bias=False),
            nn.BatchNorm2d(out), nn.ReLU(inplace=True))
        self.split: Optional[nn.ModuleList] = None  # set by split_conv, for inference

    def split_conv(self) -> None:
        """For inference after BatchNorm folding: the conv of the concatenation as the sum of a
        conv of each part, which skips writing the concatenated map (the same sum to rounding;
        24 ms less at 1024 px, where the skip is the 3-channel image)."""
        conv, n = self.layers[0], self.layers[0].in_channels - self.skip_channels
        parts = []
        for weight, bias in ((conv.weight[:, :n], conv.bias), (conv.weight[:, n:], None)):
            part = nn.Conv2d(weight.shape[1], conv.out_channels, 3, padding=1, bias=bias is not None)
            part.weight = nn.Parameter(weight.detach().clone())
            if bias is not None:
                part.bias = nn.Parameter(bias.detach().clone())
            parts.append(part)
        self.split = nn.ModuleList(parts)
        self.layers[0] = nn.Identity()  # its weights live on in the parts

    def forward(self, previous: Tensor, skip: Tensor) -> Tensor:
        up = nn.functional.interpolate(previous, scale_factor=2, mode="bilinear", align_corners=False)
        h, w = up.shape[-2:]
        if self.split is None:
            return self.layers(torch.cat([up, skip[..., :h, :w]], 1))
        out = self.split[0](up)
        out += self.split[1](skip[..., :h, :w])
        return self.layers(out)

    def unpadded(self, up: Tensor, skip: Tensor) -> Tensor:
        """The block's output from its upsampled input and skip with the conv's zero padding already
        around them (``FinestMaps.tiles``): (n, C, T + 2, T + 2) each -> (n, out, T, T)."""
        if self.split is None:
            conv = self.layers[0]
            return self.layers[1:](nn.functional.conv2d(torch.cat([up, skip], 1), conv.weight, conv.bias))
        out = nn.functional.conv2d(up, self.split[0].weight, self.split[0].bias)
        out += nn.functional.conv2d(skip, self.split[1].weight, None)
        return self.layers(out)


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
        self.memory_format = torch.contiguous_format  # of the input and weights: ``channels_last``
        self.register_buffer("mean", torch.tensor(mean).view(3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(std).view(3, 1, 1), persistent=False)

    def channels_last(self) -> "UNet":
        """In place: channels-last weights and activations, on which oneDNN's convolutions and the
        bilinear upsampling are faster on CPU (the same maps to float rounding)."""
        self.memory_format = torch.channels_last
        return self.to(memory_format=torch.channels_last)

    @property
    def compute_confidence(self) -> bool:
        return hasattr(self, "uncertainty")

    @property
    def fine_blocks(self) -> int:
        """The last decoder blocks, whose maps only the finest output level reads (the official
        network: the two at strides 2 and 1, most of a pass's time at 1,024 px)."""
        if len(self.output_scales) < 2:
            return 0
        second = sorted(self.output_scales)[1]
        return sum(len(self.decoder) - 1 - j < second for j in range(len(self.decoder)))

    def forward(self, image: Tensor, fine_dtype: Optional[torch.dtype] = None,
                defer_finest: bool = False) -> Dict[str, List[Tensor]]:
        """``fine_dtype`` (e.g. torch.bfloat16, for inference): the ``fine_blocks`` in that precision
        (autocast), their map cast back to float32 for the finest level's heads; every coarser level's
        maps are exactly those of the float32 pass. ``defer_finest`` (inference, a network whose finest
        level is at stride 1 with a decoder block of its own): the ``fine_blocks``, which only the finest
        level reads, are not run; the finest level's entries are None and ``finest`` holds a ``FinestMaps``
        that decodes it, whole or in tiles where it is read."""
        if image.dim() != 4 or image.shape[1] != 3:
            raise ValueError(f"Expected images (B, 3, H, W), got {tuple(image.shape)}.")
        min_size = 2 ** (len(self.encoder) - 1)
        if min(image.shape[-2:]) < min_size:
            raise ValueError(f"Images must be at least {min_size} px on each side, got {tuple(image.shape[-2:])}.")
        if self.crop_input:
            h, w = (s - s % min_size for s in image.shape[-2:])
            image = image[..., :h, :w]
        x = (image.contiguous(memory_format=self.memory_format) - self.mean) / self.std
        run = _checkpointed if self.grad_checkpointing and torch.is_grad_enabled() else _direct
        skips = []
        for block in self.encoder:
            x = run(block, x)
            skips.append(x)
        pre, skips = [skips[-1]], skips[:-1][::-1]  # the decoder's skips, coarse to fine
        defer = defer_finest and self.can_defer_finest and not torch.is_grad_enabled()
        decoder = self.decoder[:len(self.decoder) - self.fine_blocks] if defer else self.decoder
        exact = len(self.decoder) - (self.fine_blocks if fine_dtype is not None else 0)
        for block, skip in zip(decoder[:exact], skips):
            pre.append(run(block, pre[-1], skip))
        if exact < len(decoder):
            fine = [pre[-1].to(fine_dtype)]
            with torch.autocast(image.device.type, dtype=fine_dtype):
                for block, skip in zip(decoder[exact:], skips[exact:]):
                    fine.append(run(block, fine[-1], skip))
            pre += [x.float() if len(self.decoder) - exact - k in self.output_scales else x
                    for k, x in enumerate(fine[1:], 1)]
        finest = FinestMaps(self, pre[-1], skips[len(decoder):], fine_dtype) if defer else None
        pre = [None] * (self.fine_blocks if finest else 0) + pre[::-1]  # fine to coarse, index = log2 stride
        out = {"features": [None if pre[i] is None else adapt(pre[i])
                            for adapt, i in zip(self.adaptation, self.output_scales)]}
        if self.compute_confidence:
            out["confidences"] = [None if pre[i] is None else torch.sigmoid(-unc(pre[i]))
                                  for unc, i in zip(self.uncertainty, self.output_scales)]
        if finest:
            out["finest"] = finest
        return out

    @property
    def can_defer_finest(self) -> bool:
        """Whether ``forward`` can defer the finest level: it is at stride 1, and the last decoder
        block is read by it alone."""
        return len(self.decoder) > 0 and min(self.output_scales) == 0 and self.fine_blocks >= 1


TILE = 8  # the side in pixels of the tiles in which ``FinestMaps`` decodes the finest level
# the grid of tiles of the deferred maps before the finest starts this many cells above and left of the
# map: a finest tile (ty, tx) reads rows and columns 4 t - 1 .. 4 t + 4 of the map before it, one such
# tile for odd t and two for even t, where a grid at 0 needs two for every t (4 per finest tile, not 2.25)
STAGE_ORIGIN = 2


class FinestMaps:
    """The finest level of a UNet pass, decoded on demand (``UNet.forward(defer_finest=True)``): the
    decoder blocks that only it reads (``UNet.fine_blocks``: 3 x 3 convs of the upsampled map before
    each and of its skip) and the level's 1 x 1 heads, over the whole map (``full``) or over TILE x TILE
    tiles (``tiles``) with the convs' 1 px of context around each. A tile's values are those of the whole
    map to float rounding, so the LM can decode only the tiles it samples: at 1,024 px the blocks at
    strides 2 and 1 are most of a pass's time, and a query's points fall in about a third of the finest
    level's tiles. The maps of the blocks before the last are decoded in tiles too, into a map each,
    where a tile of the next block reads them (a third of the map at stride 2 at Cambridge settings): cells
    not decoded are left as allocated (NaN with ``poison``, which the tests turn on)."""

    poison = False  # a test hook (``pipeline.runtime.poison_undecoded``)

    def __init__(self, net: UNet, source: Tensor, skips: Sequence[Tensor], dtype: Optional[torch.dtype]):
        self.blocks = list(net.decoder)[len(net.decoder) - len(skips):]
        self.dtype, self.memory_format = dtype, net.memory_format
        level = list(net.output_scales).index(0)
        self.adapt = net.adaptation[level]
        self.uncertainty = net.uncertainty[level] if net.compute_confidence else None
        self.source = source  # (1, C, h, w): the map before the first deferred block
        h, w = source.shape[-2:]
        self.skips = [skip[..., :h << j, :w << j] for j, skip in enumerate(skips, 1)]  # each block's, cropped
        self.shape = (source.shape[0], net.output_dims[level]) + tuple(self.skips[-1].shape[-2:])
        self.grid = _grid(self.shape[-2:])  # tiles down and across
        self.stages: List[Optional[Tuple[Tensor, Tensor]]] = [None] * (len(skips) - 1)  # (map, tiles decoded)
        self.decoded = None  # what a caller decoded of it, kept with it (pipeline.localization.finest.Decoded)

    def _heads(self, x: Tensor) -> Tuple[Tensor, Optional[Tensor]]:
        x = x.float()
        return self.adapt(x), None if self.uncertainty is None else torch.sigmoid(-self.uncertainty(x))

    def _autocast(self):
        return torch.autocast(self.source.device.type, dtype=self.dtype, enabled=self.dtype is not None)

    def full(self) -> Tuple[Tensor, Optional[Tensor]]:
        """The whole level: features (B, C, H, W) and confidences (B, 1, H, W) or None, as the
        undeferred pass gives them."""
        x = self.source if self.dtype is None else self.source.to(self.dtype)
        with self._autocast():
            for block, skip in zip(self.blocks, self.skips):
                x = block(x, skip)
        return self._heads(x)

    def tiles(self, ty: Tensor, tx: Tensor) -> Tuple[Tensor, Optional[Tensor]]:
        """Tiles (ty, tx) (n,) of the first map of the batch: features (n, C, TILE, TILE) and
        confidences (n, 1, TILE, TILE) or None; tiles that overhang the map's edge hold values there too
        (the caller drops them)."""
        device = self.source.device
        return self._heads(self._block_tiles(len(self.blocks) - 1, ty.to(device), tx.to(device)))

    def _block_tiles(self, j: int, ty: Tensor, tx: Tensor, origin: int = 0) -> Tensor:
        """Deferred block j's map at tiles (ty, tx) (n,) of a grid that starts ``origin`` (even) cells above
        and left of the map: (n, C, TILE, TILE)."""
        skip = self.skips[j][0]
        H, W = skip.shape[-2:]
        h, w = H // 2, W // 2
        y0, x0 = ty * TILE - origin, tx * TILE - origin
        # the upsampled rows and columns y0 - 1 .. y0 + TILE (the conv's context) read the map before the
        # block at half-resolution rows y0 / 2 - 1 .. y0 / 2 + TILE / 2 (clamped at the map's edges, as
        # the upsampling clamps): the upsampling of that crop is the whole map's there, but for its first
        # and last rows and columns, which read past the crop
        span = torch.arange(TILE // 2 + 2, device=ty.device)
        hr, hc = ((y0 // 2 - 1)[:, None] + span).clamp(0, h - 1), ((x0 // 2 - 1)[:, None] + span).clamp(0, w - 1)
        crop = _gather(self._before(j, hr, hc), hr, hc)
        if self.dtype is not None:  # the block's input in its precision, as the whole pass has it
            crop = crop.to(self.dtype)
        with self._autocast():
            up = nn.functional.interpolate(crop, scale_factor=2, mode="bilinear", align_corners=False)
        up = up[..., 1:TILE + 3, 1:TILE + 3].contiguous(memory_format=self.memory_format)
        span = torch.arange(TILE + 2, device=ty.device)
        rows, cols = y0[:, None] - 1 + span, x0[:, None] - 1 + span
        skips = _gather(skip, rows.clamp(0, H - 1), cols.clamp(0, W - 1)).contiguous(memory_format=self.memory_format)
        # the conv's zero padding: context outside the map is zero (tiles at the map's edges)
        edge = torch.nonzero((y0 <= 0) | (x0 <= 0) | (y0 + TILE >= H) | (x0 + TILE >= W))[:, 0]
        if len(edge):
            outside = ~(((rows[edge] >= 0) & (rows[edge] < H))[:, :, None]
                        & ((cols[edge] >= 0) & (cols[edge] < W))[:, None, :])[:, None]
            up[edge] = up[edge].masked_fill(outside, 0)
            skips[edge] = skips[edge].masked_fill(outside, 0)
        with self._autocast():
            return self.blocks[j].unpadded(up, skips)

    def _before(self, j: int, rows: Tensor, cols: Tensor) -> Tensor:
        """The map (C, h, w) before deferred block j, decoded at least at rows (n, R) x cols (n, K) (ranges
        of at most TILE + 1 cells, inside the map) where it is a deferred block's own."""
        if j == 0:
            return self.source[0]
        maps, done = self._stage(j - 1)
        across = done.shape[1]
        wanted = torch.zeros(done.numel(), dtype=torch.bool, device=done.device)
        for y in ((rows[:, 0] + STAGE_ORIGIN) // TILE, (rows[:, -1] + STAGE_ORIGIN) // TILE):  # one or two tiles
            for x in ((cols[:, 0] + STAGE_ORIGIN) // TILE, (cols[:, -1] + STAGE_ORIGIN) // TILE):
                wanted[y * across + x] = True
        ids = (wanted & ~done.view(-1)).nonzero()[:, 0]
        if len(ids):
            out = self._block_tiles(j - 1, ids // across, ids % across, STAGE_ORIGIN)
            H, W = maps.shape[-2:]
            pixels, inside = tile_cells(ids // across, ids % across, H, W, STAGE_ORIGIN)
            values = out.permute(0, 2, 3, 1).reshape(-1, out.shape[1])
            write_cells(maps, pixels, values if inside is None else values[inside])
            done.view(-1)[ids] = True
        return maps

    def _stage(self, j: int) -> Tuple[Tensor, Tensor]:
        """Deferred block j's map (C, H, W), in the block's output precision and the network's layout, and
        which of its tiles are decoded (the grid): made empty on first use."""
        if self.stages[j] is None:
            H, W = self.skips[j].shape[-2:]
            shape = (H, W, self.blocks[j].out_channels)
            dtype = self.source.dtype if self.dtype is None else self.dtype
            maps = torch.full(shape, float("nan"), dtype=dtype, device=self.source.device) if self.poison \
                else torch.empty(shape, dtype=dtype, device=self.source.device)
            maps = maps.permute(2, 0, 1) if self.memory_format == torch.channels_last \
                else maps.permute(2, 0, 1).contiguous()
            grid = _grid((H + STAGE_ORIGIN, W + STAGE_ORIGIN))
            self.stages[j] = (maps, torch.zeros(grid, dtype=torch.bool, device=self.source.device))
        return self.stages[j]


def _grid(size: Tuple[int, int]) -> Tuple[int, int]:
    """The TILE x TILE tiles down and across a map of ``size`` (H, W), the last ones overhanging its edges."""
    return -(-size[0] // TILE), -(-size[1] // TILE)


def tile_cells(ty: Tensor, tx: Tensor, H: int, W: int, origin: int = 0) -> Tuple[Tensor, Optional[Tensor]]:
    """The flat cell indices (y W + x) of tiles (ty, tx) (n,) of an (H, W) map, on a grid that starts
    ``origin`` cells above and left of it, tile by tile in row order, and which of the tiles' TILE x TILE
    cells lie inside the map (None: all of them)."""
    span = torch.arange(TILE, device=ty.device) - origin
    ys = (ty[:, None] * TILE + span)[:, :, None].expand(-1, TILE, TILE).reshape(-1)
    xs = (tx[:, None] * TILE + span)[:, None, :].expand(-1, TILE, TILE).reshape(-1)
    if origin or H % TILE or W % TILE:  # tiles overhanging the map's edges
        inside = (ys >= 0) & (ys < H) & (xs >= 0) & (xs < W)
        return (ys * W + xs)[inside], inside
    return ys * W + xs, None


def write_cells(maps: Tensor, cells: Tensor, values: Tensor) -> None:
    """Write ``values`` (n, C) into the flat cells ``cells`` (n,) (y W + x) of ``maps`` (C, H, W), in place: a row
    per cell where the map is channels-last."""
    H, W = maps.shape[-2:]
    rows = maps.permute(1, 2, 0)
    if rows.is_contiguous():
        rows.view(H * W, -1).index_copy_(0, cells.to(maps.device), values.to(maps.device, maps.dtype))
    else:
        maps[:, cells // W, cells % W] = values.T.to(maps.device, maps.dtype)


def _gather(x: Tensor, rows: Tensor, cols: Tensor) -> Tensor:
    """(n, C, R, K) crops of a (C, H, W) map at rows (n, R) and columns (n, K), channels-last where the
    map is (its cells' channels contiguous: one row per cell)."""
    C, H, W = x.shape
    cells = x.permute(1, 2, 0)
    if cells.is_contiguous():
        idx = (rows[:, :, None] * W + cols[:, None, :]).reshape(-1)
        crops = cells.reshape(H * W, C).index_select(0, idx)
        return crops.reshape(len(rows), rows.shape[1], cols.shape[1], C).permute(0, 3, 1, 2)
    return x[:, rows[:, :, None], cols[:, None, :]].permute(1, 0, 2, 3)


# a network pass's precision (the maps it returns are float32 in every case): float32, bfloat16 autocast over
# the whole pass, or over ``UNet.fine_blocks`` only (the coarser levels exact)
NETWORK_PRECISIONS = {"float32": torch.float32, "bfloat16": torch.bfloat16, "bfloat16-fine": torch.bfloat16}


def predict_in_precision(net: nn.Module, image: Tensor, precision: str = "float32",
                         defer_finest: bool = False) -> Dict[str, List[Tensor]]:
    """``net``'s float32 maps of ``image`` from a pass in ``precision`` (``NETWORK_PRECISIONS``); a network
    without a decoder (the photometric one) has no finest blocks and runs ``bfloat16-fine`` in float32.
    ``defer_finest``: a UNet's finest level decoded on demand (``UNet.forward``), in float32 and
    ``bfloat16-fine``."""
    if precision not in NETWORK_PRECISIONS:
        raise ValueError(f"precision must be one of {sorted(NETWORK_PRECISIONS)}, got {precision!r}.")
    if not isinstance(net, UNet):
        return net(image)
    if precision == "float32":
        return net(image, defer_finest=defer_finest)
    if precision == "bfloat16-fine":
        return net(image, fine_dtype=NETWORK_PRECISIONS[precision], defer_finest=defer_finest)
    with torch.autocast(image.device.type, dtype=NETWORK_PRECISIONS[precision]):
        pred = net(image)
    return {key: [x.float() for x in maps] for key, maps in pred.items()}


def fold_batchnorm(module: nn.Module) -> nn.Module:
    """Fold, in place, every BatchNorm2d that follows a Conv2d in a Sequential into that conv
    (its running statistics become the conv's scale and bias), for inference only: the same
    outputs to float rounding, one pass over each activation fewer."""
    for seq in module.modules():
        if isinstance(seq, nn.Sequential):
            for i in range(len(seq) - 1):
                if isinstance(seq[i], nn.Conv2d) and isinstance(seq[i + 1], nn.BatchNorm2d):
                    seq[i] = fuse_conv_bn_eval(seq[i], seq[i + 1])
                    seq[i + 1] = nn.Identity()
    return module


class PointwiseConv(nn.Module):
    """A 1x1 convolution run by oneDNN, for inference on channels-last CPU maps: on one thread
    and a batch of one, PyTorch sends 1x1 convs to a slower path that also returns them in the
    default layout (a copy, and slower sampling and normalisation of the maps downstream).

    Under bfloat16 autocast (``--network-precision bfloat16``) on a CPU where oneDNN has no bfloat16 path
    (it needs AVX-512 or AVX-NE-CONVERT), the conv goes through ``conv2d``, which autocast runs in bfloat16
    everywhere, emulated where the CPU has no such instructions."""

    def __init__(self, conv: nn.Conv2d):
        super().__init__()
        self.weight, self.bias = conv.weight, conv.bias

    def forward(self, x: Tensor) -> Tensor:
        if x.dtype != torch.float32 and not onednn_bfloat16():
            return nn.functional.conv2d(x, self.weight, self.bias)
        return torch.ops.aten.mkldnn_convolution(x, self.weight, self.bias, [0, 0], [1, 1], [1, 1], 1)


@functools.lru_cache(maxsize=None)
def onednn_bfloat16() -> bool:
    """Whether oneDNN's convolutions run in bfloat16 on this CPU (its bfloat16 kernels need AVX-512 or
    AVX-NE-CONVERT; without them they refuse the input)."""
    return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())


def _pointwise_convs(module: nn.Module) -> None:
    for parent in list(module.modules()):
        for name, child in parent.named_children():
            if isinstance(child, nn.Conv2d) and child.kernel_size == (1, 1) and child.stride == (1, 1) \
                    and child.groups == 1 and child.padding == (0, 0) and child.weight.dtype == torch.float32:
                setattr(parent, name, PointwiseConv(child))


def prepare_for_inference(net: nn.Module, device: str = "cpu") -> nn.Module:
    """A UNet made faster for inference, in place: eval mode, BatchNorm folded, the decoder's
    convs split (``DecoderBlock.split_conv``) and, on CPU, channels-last activations, on which
    oneDNN's convolutions and the bilinear upsampling are faster, with 1x1 convs through oneDNN
    (``PointwiseConv``). The same maps to float rounding; with ``pipeline.runtime.keep_freed_memory``
    a 1024 px pass on one core takes about 0.3 s instead of 0.53 (docs/benchmarks.md, "The CPU
    query"). Other networks (the photometric one) are returned as they are. Not for training:
    the folded convs no longer learn BatchNorm statistics."""
    if not isinstance(net, UNet):
        return net
    fold_batchnorm(net.eval())
    for block in net.decoder:
        block.split_conv()
    if torch.device(device).type == "cpu":
        net.channels_last()
        if torch.backends.mkldnn.is_available():
            _pointwise_convs(net)
    return net


def vgg_unet(encoder: str = "vgg19", **kwargs) -> UNet:
    """The official PixLoc network with a VGG encoder (random init; load a checkpoint)."""
    blocks, skip_dims = vgg_blocks(encoder)
    return UNet(blocks, skip_dims, **kwargs)
