"""Direct photometric alignment: the image's own colours as features (the paper's first
ablation row, Table 6), with the same levels as the learned networks and no confidence."""

from typing import Dict, List, Sequence

from torch import Tensor, nn
from torch.nn.functional import avg_pool2d


class PhotometricExtractor(nn.Module):
    """RGB in [0, 1] as 3-channel features at strides ``strides`` (finest first), each level
    the image averaged over stride x stride blocks. No parameters."""

    def __init__(self, strides: Sequence[int] = (1, 4, 16)):
        super().__init__()
        self.strides = tuple(strides)
        self.output_dims = (3,) * len(self.strides)
        self.compute_confidence = False

    def forward(self, image: Tensor) -> Dict[str, List[Tensor]]:
        if image.dim() != 4 or image.shape[1] != 3:
            raise ValueError(f"Expected images (B, 3, H, W), got {tuple(image.shape)}.")
        return {"features": [image if s == 1 else avg_pool2d(image, s) for s in self.strides]}
