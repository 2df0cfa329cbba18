"""Map points from depth: RGB-D maps (frame sampling or open3d TSDF fusion) and SfM densification.

Sarlin et al. 2021, appendix "Accuracy of the 3D model": SfM points are moved
to the back-projection of one of their observations at the interpolated depth.
"""

import dataclasses
import logging
from typing import List, Tuple

import numpy as np
import torch

from pipeline.images import ImageReadError, read_depth
from pipeline.scene import ImageRecord, Scene, SceneError

logger = logging.getLogger(__name__)


def depth_camera(image: ImageRecord):
    return (image.depth_camera or image.camera).to_pixloc(torch.float64)


def load_depth(image: ImageRecord) -> np.ndarray:
    if image.depth_path is None:
        raise SceneError(f"Image {image.name} has no depth map.")
    return read_depth(image.depth_path, image.depth_scale)


def _to_world(T: np.ndarray, p_cam: np.ndarray) -> np.ndarray:
    return (p_cam - T[:, 3]) @ T[:, :3]


def _to_frame(T: np.ndarray, p_world: np.ndarray) -> np.ndarray:
    return p_world @ T[:, :3].T + T[:, 3]


def backproject(image: ImageRecord, depth: np.ndarray, stride: int = 1) -> np.ndarray:
    """World points (K, 3) of the valid depth pixels on a grid of ``stride`` pixels (from the
    depth sensor's pose)."""
    cam = depth_camera(image)
    v, u = np.mgrid[0:depth.shape[0]:stride, 0:depth.shape[1]:stride]
    d = depth[v, u]
    keep = d > 0
    p2d = torch.from_numpy(np.stack([u[keep], v[keep]], -1).astype(np.float64))
    rays = cam.image2cam(p2d).numpy()
    return _to_world(image.depth_from_world(), rays * d[keep][:, None])


def readable_depths(images: List[ImageRecord]) -> List[ImageRecord]:
    """The frames, each whose depth file cannot be read whole, or is not of its depth camera's size,
    with a ``problem``: it is left out of the points and observations, and the build records it as
    failed with the reason, instead of stopping the whole map. A warning names each. (Each depth map is
    decoded here and again where it is used: holding every frame's would take GBs on large maps.)"""
    out = []
    for im in images:
        try:
            depth = load_depth(im)
            cam = im.depth_camera or im.camera
            if depth.shape != (cam.height, cam.width):
                raise ImageReadError(f"depth file {im.depth_path} is {depth.shape[1]}x{depth.shape[0]}, "
                                     f"not the {cam.width}x{cam.height} of its camera")
            out.append(im)
        except ImageReadError as e:
            logger.warning("RGB-D frame %s left out of the map: %s", im.name, e)
            out.append(dataclasses.replace(im, problem=str(e)))
    return out


def frame_points(images: List[ImageRecord], stride: int = 16) -> np.ndarray:
    """Map points sampled from every ``stride``-th pixel of each depth frame (but those with a
    ``problem``: ``readable_depths``)."""
    return np.concatenate([backproject(im, load_depth(im), stride) for im in images if im.problem is None]
                          or [np.zeros((0, 3))])


def tsdf_points(images: List[ImageRecord], voxel: float = 0.02, truncation: float = 0.08,
                max_depth: float = 5.0, max_resolution: int = 512) -> np.ndarray:
    """Points on the surface of an open3d TSDF fusion of the depth frames.

    A uniform volume bounds the frames' back-projected points (open3d's
    scalable volumes returned no surface in our tests with open3d 0.20); its
    voxel is ``voxel`` unless the scene needs more than ``max_resolution``
    voxels per side.
    """
    import open3d as o3d

    images = [im for im in images if im.problem is None]  # ``readable_depths``
    depths = [load_depth(im) for im in images]
    for d in depths:
        d[d > max_depth] = 0
    sample = np.concatenate([backproject(im, d, 8) for im, d in zip(images, depths)])
    if len(sample) == 0:
        raise SceneError("The depth frames have no valid depth.")
    lo, hi = np.percentile(sample, 0.5, axis=0) - truncation, np.percentile(sample, 99.5, axis=0) + truncation
    length = float((hi - lo).max())
    resolution = int(min(max_resolution, np.ceil(length / voxel)))
    volume = o3d.pipelines.integration.UniformTSDFVolume(
        length=length, resolution=resolution, sdf_trunc=truncation,
        color_type=o3d.pipelines.integration.TSDFVolumeColorType.RGB8, origin=lo.reshape(3, 1))
    for im, depth in zip(images, depths):
        cam = im.depth_camera or im.camera
        if cam.model not in ("PINHOLE", "SIMPLE_PINHOLE"):
            raise SceneError(f"TSDF fusion needs pinhole depth cameras, {im.name} has {cam.model}.")
        fx, fy, cx, cy = cam.params if cam.model == "PINHOLE" else (cam.params[0], *cam.params)
        intrinsic = o3d.camera.PinholeCameraIntrinsic(cam.width, cam.height, fx, fy, cx - 0.5, cy - 0.5)
        color = np.zeros(depth.shape + (3,), np.uint8)
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(color), o3d.geometry.Image(depth), depth_scale=1.0, depth_trunc=max_depth,
            convert_rgb_to_intensity=False)
        extrinsic = np.eye(4)
        extrinsic[:3] = im.depth_from_world()
        volume.integrate(rgbd, intrinsic, extrinsic)
    cloud = volume.extract_point_cloud().voxel_down_sample(length / resolution)
    return np.asarray(cloud.points, dtype=np.float64)


def observe(points: np.ndarray, images: List[ImageRecord], tolerance: float = 0.03,
            cull: bool = True) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Observations of ``points`` in ``images`` by projection and a depth test.

    A point is observed where it projects inside the image and its depth in the
    depth sensor agrees with the depth map (nearest pixel) within ``tolerance``
    times the depth. Returns (point index, image index, xy in COLMAP pixel
    coordinates). With ``cull``, each image tests only the points within reach of
    its depth map (``_within_reach``, a k-d tree), not every point of the map: the
    same observations, in time that grows with the map instead of its square.
    """
    tree = None
    if cull and len(images) > 1 and len(points):
        import open3d as o3d
        tree = o3d.geometry.KDTreeFlann(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)))
    obs_point, obs_image, obs_xy = [], [], []
    for i, im in enumerate(images):
        if im.problem is not None:  # a frame left out (``readable_depths``): it observes nothing
            continue
        depth = load_depth(im)
        cand = _within_reach(tree, im, depth, tolerance) if tree is not None else None
        sub = points if cand is None else points[cand]
        p_depth = torch.from_numpy(_to_frame(im.depth_from_world(), sub))
        p2d_d, valid_d = depth_camera(im).cam2image(p_depth)
        uv = np.round(p2d_d.numpy()).astype(np.int64)
        inside = valid_d.numpy() & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & \
            (uv[:, 0] < depth.shape[1]) & (uv[:, 1] < depth.shape[0])
        d = np.zeros(len(sub))
        d[inside] = depth[uv[inside, 1], uv[inside, 0]]
        z = p_depth[:, 2].numpy()
        visible = inside & (d > 0) & (np.abs(z - d) < tolerance * d)
        p_cam = torch.from_numpy(_to_frame(np.asarray(im.cam_from_world, np.float64), sub))
        p2d, valid = im.camera.to_pixloc(torch.float64).cam2image(p_cam)
        keep = np.flatnonzero(visible & valid.numpy())
        obs_point.append(keep if cand is None else cand[keep])
        obs_image.append(np.full(len(keep), i))
        obs_xy.append(p2d.numpy()[keep] + 0.5)  # pixloc -> COLMAP pixel convention
    return np.concatenate(obs_point), np.concatenate(obs_image), np.concatenate(obs_xy)


def _within_reach(tree, image: ImageRecord, depth: np.ndarray, tolerance: float) -> np.ndarray:
    """Sorted indices of the points that ``image``'s depth test could keep: a kept point has a depth
    z < (1 + tolerance) x the map's largest depth and projects inside the image, so it lies within
    z x the longest ray to an image corner (unit depth) of the sensor, plus a margin for distortion."""
    h, w = depth.shape
    corners = torch.tensor([[0.0, 0.0], [w, 0.0], [0.0, h], [w, h], [w / 2, 0.0], [0.0, h / 2]], dtype=torch.float64)
    rays = depth_camera(image).image2cam(corners).numpy()
    longest = float(np.sqrt(1 + (rays[:, :2] ** 2).sum(1)).max())
    radius = float(depth.max()) * (1 + tolerance) * longest * 1.1
    T = image.depth_from_world()
    centre = -T[:, :3].T @ T[:, 3]
    _, idx, _ = tree.search_radius_vector_3d(centre, radius)
    return np.sort(np.asarray(idx, dtype=np.int64))


def rgbd_scene(images: List[ImageRecord], method: str = "tsdf", min_track_length: int = 2,
               stride: int = 16, voxel: float = 0.02, tolerance: float = 0.03) -> Scene:
    """A map from posed RGB-D frames: points from the frames or a TSDF, observed by projection.

    Points seen in fewer than ``min_track_length`` images are dropped.
    """
    if method not in ("tsdf", "frames"):
        raise ValueError(f"Unknown RGB-D point method {method!r}: use 'tsdf' or 'frames'.")
    images = readable_depths(images)
    if all(im.problem is not None for im in images):
        raise SceneError(f"None of the {len(images)} depth frames can be read (first: {images[0].problem}).")
    points = tsdf_points(images, voxel=voxel) if method == "tsdf" else frame_points(images, stride=stride)
    if len(points) == 0:
        raise SceneError("The depth frames produced no 3D points.")
    obs_point, obs_image, obs_xy = observe(points, images, tolerance=tolerance)
    track = np.bincount(obs_point, minlength=len(points))
    keep = np.flatnonzero(track >= min_track_length)
    remap = -np.ones(len(points), dtype=np.int64)
    remap[keep] = np.arange(len(keep))
    sel = remap[obs_point] >= 0
    logger.info("RGB-D map: %d of %d points seen in >= %d images.", len(keep), len(points), min_track_length)
    return Scene(images, points[keep], remap[obs_point[sel]], obs_image[sel], obs_xy[sel])


def densify(scene: Scene, min_depth: float = 1e-3) -> Scene:
    """Move each SfM point to the back-projection of its first observation at the
    bilinearly interpolated depth of that image (points without valid depth stay).
    The depth must be taken at the image's pose (no ``color_from_depth``): a ray of
    the image then meets the depth map at one pixel."""
    apart = [im.name for im in scene.images if im.color_from_depth is not None]
    if apart:
        raise SceneError(f"Densification needs depth taken at the image's pose; {len(apart)} images have their "
                         f"depth sensor apart (e.g. {apart[0]}): build from the RGB-D frames instead.")
    points = scene.points.copy()
    moved = np.zeros(len(points), dtype=bool)
    order = np.argsort(scene.obs_point, kind="stable")
    first = order[np.unique(scene.obs_point[order], return_index=True)[1]]
    for i, im in enumerate(scene.images):
        sel = first[scene.obs_image[first] == i]
        if len(sel) == 0 or im.depth_path is None:
            continue
        depth = load_depth(im)
        # The observation's ray, then where it falls in the depth map (same pose,
        # possibly other intrinsics when depth is not registered to colour).
        rays = im.camera.to_pixloc(torch.float64).image2cam(torch.from_numpy(scene.obs_xy[sel] - 0.5))
        xy, in_front = depth_camera(im).cam2image(rays)
        xy, rays = xy.numpy(), rays.numpy()
        x0, y0 = np.floor(xy[:, 0]).astype(int), np.floor(xy[:, 1]).astype(int)
        ok = in_front.numpy() & (x0 >= 0) & (y0 >= 0) & (x0 + 1 < depth.shape[1]) & (y0 + 1 < depth.shape[0])
        fx, fy = xy[:, 0] - x0, xy[:, 1] - y0
        x0c, y0c = np.clip(x0, 0, depth.shape[1] - 2), np.clip(y0, 0, depth.shape[0] - 2)
        corners = np.stack([depth[y0c, x0c], depth[y0c, x0c + 1], depth[y0c + 1, x0c], depth[y0c + 1, x0c + 1]])
        d = (corners[0] * (1 - fx) * (1 - fy) + corners[1] * fx * (1 - fy)
             + corners[2] * (1 - fx) * fy + corners[3] * fx * fy)
        ok &= (corners > min_depth).all(0)  # no interpolation across holes
        points[scene.obs_point[sel[ok]]] = _to_world(np.asarray(im.cam_from_world), rays[ok] * d[ok][:, None])
        moved[scene.obs_point[sel[ok]]] = True
    logger.info("Densification moved %d of %d points.", int(moved.sum()), len(points))
    return Scene(scene.images, points, scene.obs_point, scene.obs_image, scene.obs_xy, scene.point_ids)
