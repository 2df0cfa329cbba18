"""Reference features at map-point observations, sampled as the official localizer samples them.

For each image scale (official ``multiscale``: target size = resize // s),
the image is downscaled so that its longer side is at most the target, the
network runs once, and every level's raw (not normalised) features and
confidence are bilinearly sampled at the projection of each 3D point the
image observes, with the level's camera. An observation is valid at a level
when it projects inside the image and inside the interpolation margin.
"""

import logging

import numpy as np
import torch

from pixloc.interpolation import Interpolator
from pixloc.nets.unet import UNet

from pipeline.descriptors import global_descriptor
from pipeline.images import read_image_for, resize_max, to_tensor
from pipeline.keypoints import MAX_FEATURES, MAX_GAP, extract_sift, observation_descriptors
from pipeline.scene import ImageRecord
from pipeline.store.schema import COMPACT_PCA, DTYPES, FeatureConfig, ImageFeatures  # noqa: F401 (where they were)

logger = logging.getLogger(__name__)


@torch.no_grad()
def extract_image_features(net: UNet, conf: FeatureConfig, image: ImageRecord, p3d_world: np.ndarray,
                           device: str = "cpu") -> ImageFeatures:
    """Sample the features of ``image`` at the projections of ``p3d_world`` (K, 3)."""
    rgb, camera, note = read_image_for(image.path, image.camera)  # the same size rule as queries
    if note:
        logger.warning("Map image %s: %s", image.name, note)
    camera = camera.to_pixloc(torch.float64)
    p3d_cam = image.pose(torch.float64).transform(torch.from_numpy(np.asarray(p3d_world, np.float64)))
    interpolator = Interpolator("linear", conf.pad)
    samples, descriptor = {}, None
    for k, image_scale in enumerate(conf.image_scales):
        resized, (sx, sy) = resize_max(rgb, conf.resize // image_scale)
        pred = net(to_tensor(resized)[None].to(device))
        for level, stride in enumerate(net.strides):
            cam = camera.scale((sx / stride, sy / stride))
            p2d, visible = cam.cam2image(p3d_cam)
            fmap = pred["features"][level][0]
            values, inside, _ = interpolator(fmap, p2d.to(fmap))
            conf_map = pred["confidences"][level][0] if "confidences" in pred else torch.ones_like(fmap[:1])
            confidence, _, _ = interpolator(conf_map, p2d.to(fmap))
            samples[(k, level)] = (values.cpu().numpy(), confidence[:, 0].cpu().numpy(),
                                   (inside & visible.to(inside.device)).cpu().numpy())
        if image_scale == 1 or k == len(conf.image_scales) - 1:
            descriptor = global_descriptor(pred["features"][-1][0], conf.descriptor).cpu().numpy()
    sift = None
    if conf.sift:  # keypoints and observations in the pixels of the image read (COLMAP convention)
        p2d, visible = camera.cam2image(p3d_cam)
        observed = np.where(visible.numpy()[:, None], p2d.numpy() + 0.5, np.nan)
        sift = observation_descriptors(*extract_sift(rgb, conf.sift, MAX_FEATURES), observed, MAX_GAP)
    return ImageFeatures(samples, descriptor, sift)

