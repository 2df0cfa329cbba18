"""A seeded synthetic scene: a courtyard of textured buildings, poles and trees, rendered on CPU
with open3d's RaycastingScene into images with depth, exact poses and intrinsics, under
appearance conditions ``day``, ``dusk``, ``night`` and ``occluded``.

Rays are generated with our own Camera and Pose (pixel origin at the top-left pixel's
centre), so rendered pixels and projections agree by construction; textures are procedural
functions of the 3D hit point, so they are consistent across views.
"""

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Tuple

import numpy as np
import torch

from pipeline.scene import CameraRecord, ImageRecord

logger = logging.getLogger(__name__)

CONDITIONS = ("day", "dusk", "night", "occluded")
GROUND, PLASTER, BRICK, POLE, TRUNK, FOLIAGE, OCCLUDER = range(7)


def box_mesh(center, size) -> Tuple[np.ndarray, np.ndarray]:
    c, s = np.asarray(center, float), np.asarray(size, float) / 2
    v = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * s + c
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return v, f


def _hash(*coords) -> np.ndarray:
    h = np.zeros_like(coords[0], dtype=np.float64)
    for i, c in enumerate(coords):
        h = h + c * (12.9898 + 65.233 * i)
    return np.modf(np.abs(np.sin(h) * 43758.5453))[0]


def value_noise(x: np.ndarray, y: np.ndarray, octaves: int = 3) -> np.ndarray:
    """Smooth pseudo-random noise in [0, 1] of 2D coordinates (a few octaves)."""
    out, amp, total = np.zeros_like(x), 1.0, 0.0
    for o in range(octaves):
        fx, fy = x * 2 ** o, y * 2 ** o
        ix, iy = np.floor(fx), np.floor(fy)
        tx, ty = fx - ix, fy - iy
        tx, ty = tx * tx * (3 - 2 * tx), ty * ty * (3 - 2 * ty)
        a, b = _hash(ix, iy), _hash(ix + 1, iy)
        c, d = _hash(ix, iy + 1), _hash(ix + 1, iy + 1)
        out += amp * (a + (b - a) * tx + (c - a) * ty + (a - b - c + d) * tx * ty)
        total += amp
        amp *= 0.5
    return out / total


@dataclass(frozen=True)
class SyntheticConfig:
    """seed: everything random derives from it. size: courtyard side in metres.
    textures: photos (paths) whose crops cover some facades instead of procedural plaster;
    ``texture_scale``: metres per texture image width."""

    seed: int = 0
    size: float = 30.0
    num_poles: int = 6
    num_trees: int = 5
    textures: Tuple[str, ...] = ()
    texture_scale: float = 8.0


class SyntheticScene:
    """Triangle meshes with a material and an object id per triangle, ready for ray casting."""

    photo_every_facade = False  # photo textures (``textures``) on half the plaster buildings only

    def __init__(self, conf: SyntheticConfig = SyntheticConfig()):
        rng = np.random.default_rng(conf.seed)
        self.conf = conf
        parts: List[Tuple[np.ndarray, np.ndarray, int]] = []
        S = conf.size
        parts.append((np.array([[-S, -S, 0], [S, -S, 0], [S, S, 0], [-S, S, 0]], float),
                      np.array([[0, 1, 2], [0, 2, 3]]), GROUND))
        half = S / 2
        for side in range(4):  # buildings along the four sides of the courtyard
            x = -half + 2
            while x < half - 2:
                w = rng.uniform(5, 10)
                h = rng.uniform(7, 16)
                d = rng.uniform(5, 8)
                along = min(x + w / 2, half - 2)
                c = np.array([along, half + d / 2, h / 2])
                R = np.array([[np.cos(side * np.pi / 2), -np.sin(side * np.pi / 2), 0],
                              [np.sin(side * np.pi / 2), np.cos(side * np.pi / 2), 0], [0, 0, 1]])
                v, f = box_mesh(c, (w - 0.3, d, h))
                parts.append((v @ R.T, f, PLASTER if rng.random() < 0.6 else BRICK))
                x += w
        for _ in range(conf.num_poles):
            p = rng.uniform(-half + 3, half - 3, 2)
            parts.append((*box_mesh((*p, 2.5), (0.15, 0.15, 5.0)), POLE))
        for _ in range(conf.num_trees):
            p = rng.uniform(-half + 4, half - 4, 2)
            parts.append((*box_mesh((*p, 1.5), (0.4, 0.4, 3.0)), TRUNK))
            parts.append((*box_mesh((*p, 4.0), (2.5, 2.5, 2.5)), FOLIAGE))
        self.parts = parts
        self.lamps = np.array([[*rng.uniform(-half + 3, half - 3, 2), 4.5] for _ in range(6)])
        self.textures = [load_texture(p) for p in conf.textures]

    def _raycaster(self, extra: List = ()):
        import open3d as o3d
        scene = o3d.t.geometry.RaycastingScene()
        material = []
        for v, f, m in list(self.parts) + list(extra):  # one geometry per part: its id indexes ``material``
            scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
            material.append(m)
        return scene, np.array(material)

    def reference_poses(self, n: int, height: float = 1.6) -> List[np.ndarray]:
        """Cameras on a circle around the courtyard centre, looking outwards at the facades."""
        angles = np.linspace(0, 2 * np.pi, n, endpoint=False)
        return [look_at(np.array([4 * np.cos(a), 4 * np.sin(a), height]),
                        np.array([20 * np.cos(a), 20 * np.sin(a), height + 2])) for a in angles]

    def query_poses(self, n: int, seed: int, spread: float = 1.0) -> List[np.ndarray]:
        """Other viewpoints: off the reference circle (radius 4 m + spread x [-1.5, 2.5] m),
        other heights and headings (spread x [-0.4, 0.4] rad off the radial direction)."""
        rng = np.random.default_rng(seed)
        poses = []
        for _ in range(n):
            a = rng.uniform(0, 2 * np.pi)
            r = 4 + spread * rng.uniform(-1.5, 2.5)
            eye = np.array([r * np.cos(a), r * np.sin(a), rng.uniform(1.3, 2.2)])
            heading = a + spread * rng.uniform(-0.4, 0.4)
            poses.append(look_at(eye, eye + np.array([np.cos(heading), np.sin(heading), rng.uniform(0.05, 0.2)])))
        return poses

    def render(self, camera: CameraRecord, cam_from_world: np.ndarray, condition: str = "day",
               seed: int = 0) -> Tuple[np.ndarray, np.ndarray]:
        """(H, W, 3) uint8 RGB and (H, W) float32 depth along the optical axis (0 = sky)."""
        import open3d as o3d
        if condition not in CONDITIONS:
            raise ValueError(f"Unknown condition {condition!r}; known: {', '.join(CONDITIONS)}.")
        rng = np.random.default_rng(seed)
        T = np.asarray(cam_from_world, float)
        R, t = T[:, :3], T[:, 3]
        extra = []
        if condition == "occluded":  # objects in front of the camera
            for _ in range(3):
                p_cam = np.array([rng.uniform(-1.5, 1.5), rng.uniform(-0.5, 1.0), rng.uniform(1.5, 3.5)])
                extra.append((*box_mesh(R.T @ (p_cam - t), rng.uniform(0.4, 1.2, 3)), OCCLUDER))
        if extra:
            scene, material = self._raycaster(extra)
        else:  # built once: a city has thousands of parts
            if getattr(self, "_static", None) is None:
                self._static = self._raycaster()
            scene, material = self._static
        cam = camera.to_pixloc(torch.float64)
        v, u = np.mgrid[0:camera.height, 0:camera.width]
        p2d = torch.from_numpy(np.stack([u, v], -1).reshape(-1, 2).astype(np.float64))
        dirs_cam = cam.image2cam(p2d).numpy()
        dirs = dirs_cam @ R  # world directions (R^T d)
        origin = -R.T @ t
        rays = np.concatenate([np.broadcast_to(origin, dirs.shape), dirs], 1).astype(np.float32)
        hit = scene.cast_rays(o3d.core.Tensor(rays))
        t_hit = hit["t_hit"].numpy().astype(np.float64)
        geom = hit["geometry_ids"].numpy().astype(np.int64)
        normal = hit["primitive_normals"].numpy().astype(np.float64)
        ok = np.isfinite(t_hit)
        depth = np.where(ok, t_hit, 0.0)  # rays have z = 1 in the camera: t is the depth
        X = origin + dirs * np.where(ok, t_hit, 0)[:, None]
        oid = np.where(ok, geom, -1)
        mat = np.where(ok, material[np.where(ok, geom, 0)], -1)
        color = _albedo(X, normal, mat, oid)
        if getattr(self.conf, "detail", 0.0) > 0:
            color = _weathering(color, X, normal, ok, self.conf.detail)
        if self.textures:
            color = _photo_facades(color, X, normal, mat, oid, self.textures, self.conf.texture_scale,
                                   self.photo_every_facade)
        lamps = self.lamps
        if len(lamps) > 16:  # a city: the lamps near the camera light what it sees
            lamps = lamps[np.argsort(np.linalg.norm(lamps - origin, axis=1))[:16]]
        color = _light(color, X, normal, ok, condition, lamps, dirs, rng)
        image = color.reshape(camera.height, camera.width, 3)
        if condition in ("dusk", "night"):
            import cv2
            image = cv2.GaussianBlur(image.astype(np.float32), (0, 0), 0.8 if condition == "dusk" else 1.2)
            image = image + rng.normal(0, 0.02 if condition == "dusk" else 0.04, image.shape)
        if condition == "night":  # auto-exposure, as a camera at night: brighter, and noisier
            image = image * np.clip(0.16 / max(float(image.mean()), 1e-3), 1.0, 3.0)
        return (np.clip(image, 0, 1) * 255).round().astype(np.uint8), depth.reshape(
            camera.height, camera.width).astype(np.float32)


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """cam_from_world (3, 4) of a camera at ``eye`` looking at ``target`` (x right, y down, z forward)."""
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return np.concatenate([R, (-R @ eye)[:, None]], 1)


def load_texture(path, max_side: Optional[int] = None) -> np.ndarray:
    """A photo as a texture in [0, 1]; at most ``max_side`` pixels on its longer side if given."""
    from pipeline.images import read_image, resize_max
    rgb = read_image(path)
    if max_side:
        rgb = resize_max(rgb, max_side)[0]
    return rgb.astype(np.float64) / 255.0


def _photo_facades(color, X, n, mat, oid, textures, scale, every_facade: bool = False) -> np.ndarray:
    """Half of the plaster buildings (by object id), or with ``every_facade`` every building,
    take a photo as facade texture, tiled along the wall (u) and the height (z), ``scale``
    metres per texture width."""
    tangent = np.stack([-n[:, 1], n[:, 0], np.zeros(len(n))], 1)
    u, z = (X * tangent).sum(1), X[:, 2]
    out = color.copy()
    for k, tex in enumerate(textures):
        h, w = tex.shape[:2]
        if every_facade:
            sel = ((mat == PLASTER) | (mat == BRICK)) & (oid % len(textures) == k)
        else:
            sel = (mat == PLASTER) & (oid % 2 == 0) & ((oid // 2) % len(textures) == k)
        px = (np.mod(u[sel] / scale, 1.0) * (w - 1)).astype(np.int64)
        py = ((1 - np.mod(z[sel] / (scale * h / w), 1.0)) * (h - 1)).astype(np.int64)
        out[sel] = tex[py, px]
    return out


def _weathering(color, X, n, ok, amount: float) -> np.ndarray:
    """Fine stains on every surface (value noise of 6 and 12 cycles per metre, in wall or ground
    coordinates), albedo scaled by 1 +- ``amount``: texture that local features (SIFT) can tell
    apart, where the procedural walls repeat (windows, bricks) or are plain."""
    tangent = np.stack([-n[:, 1], n[:, 0], np.zeros(len(n))], 1)
    ground = np.abs(n[:, 2]) > 0.5
    a = np.where(ground, X[:, 0], (X * tangent).sum(1))
    b = np.where(ground, X[:, 1], X[:, 2])
    stain = value_noise(a * 6.0, b * 6.0, octaves=2)
    return np.where(ok[:, None], color * (1 - amount + 2 * amount * stain)[:, None], color)


def _albedo(X, n, mat, oid) -> np.ndarray:
    c = np.zeros((len(X), 3))
    tint = 0.75 + 0.25 * _hash(oid.astype(float) + 0.5, oid.astype(float) * 3.1)[:, None]
    # facade coordinates: along the wall and height
    tangent = np.stack([-n[:, 1], n[:, 0], np.zeros(len(n))], 1)
    u = (X * tangent).sum(1)
    z = X[:, 2]
    g = mat == GROUND
    cobble = value_noise(X[g, 0] * 2, X[g, 1] * 2)
    grid = (np.abs(np.modf(X[g, 0] * 2)[0]) < 0.06) | (np.abs(np.modf(X[g, 1] * 2)[0]) < 0.06)
    c[g] = (0.35 + 0.3 * cobble[:, None] - 0.15 * grid[:, None]) * np.array([0.9, 0.85, 0.8])
    p = mat == PLASTER
    cell_u, cell_z = np.modf(np.abs(u[p]) / 3.0)[0], np.modf(z[p] / 3.2)[0]
    window = (cell_u > 0.25) & (cell_u < 0.75) & (cell_z > 0.3) & (cell_z < 0.8) & (z[p] > 1.0)
    base = (0.75 + 0.2 * value_noise(u[p] * 1.5, z[p] * 1.5))[:, None] * np.array([0.95, 0.85, 0.7]) * tint[p]
    glass = np.array([0.15, 0.2, 0.3]) * (0.7 + 0.6 * value_noise(u[p] * 4, z[p] * 4))[:, None]
    c[p] = np.where(window[:, None], glass, base)
    b = mat == BRICK
    row = np.floor(z[b] / 0.25)
    mortar = (np.modf(z[b] / 0.25)[0] < 0.12) | (np.modf((u[b] + 0.25 * (row % 2)) / 0.5)[0] < 0.06)
    shade = 0.8 + 0.4 * _hash(np.floor((u[b] + 0.25 * (row % 2)) / 0.5), row)
    c[b] = np.where(mortar[:, None], 0.75, (shade[:, None] * np.array([0.6, 0.28, 0.2]))) * tint[b]
    c[mat == POLE] = np.array([0.3, 0.32, 0.35])
    c[mat == TRUNK] = np.array([0.35, 0.25, 0.15])
    f = mat == FOLIAGE
    leaves = value_noise(X[f, 0] * 3 + X[f, 2], X[f, 1] * 3 - X[f, 2])
    c[f] = (0.5 + 0.5 * leaves)[:, None] * np.array([0.2, 0.45, 0.15])
    o = mat == OCCLUDER
    c[o] = (0.4 + 0.4 * _hash(oid[o].astype(float), 1.0))[:, None] * np.array([0.9, 0.4, 0.3])
    return c


def _light(albedo, X, n, ok, condition, lamps, dirs, rng) -> np.ndarray:
    # (direction, strength and colour of the sun or moon, ambient light); at night, lamps too
    sun = {"day": ([0.4, 0.3, 0.85], 1.0, 0.45, [1, 1, 1]), "occluded": ([0.4, 0.3, 0.85], 1.0, 0.45, [1, 1, 1]),
           "dusk": ([-0.7, 0.5, 0.25], 0.7, 0.25, [1.0, 0.7, 0.45]),
           "night": ([0.3, -0.2, 0.9], 0.12, 0.1, [0.6, 0.7, 1.0])}
    direction, strength, ambient, tint = sun[condition]
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    facing = np.where((n * dirs).sum(1, keepdims=True) > 0, -n, n)  # normals towards the camera
    lambert = np.clip((facing * d).sum(1), 0, None)[:, None]
    light = (ambient + strength * lambert) * np.asarray(tint)
    if condition == "night":
        for lamp in lamps:
            v = lamp - X
            dist2 = (v * v).sum(1, keepdims=True)
            light = light + 8.0 * np.clip((facing * v).sum(1, keepdims=True), 0, None) / dist2 ** 1.5 * np.array(
                [1.0, 0.85, 0.6])
    color = albedo * light
    sky = {"day": [0.55, 0.7, 0.95], "occluded": [0.55, 0.7, 0.95], "dusk": [0.9, 0.55, 0.35],
           "night": [0.03, 0.04, 0.08]}[condition]
    return np.where(ok[:, None], color, np.asarray(sky) * (0.9 + 0.1 * dirs[:, 2:3].clip(0, 1)))


def area(cam_from_world: np.ndarray, num_areas: int = 8) -> str:
    """The coarse location group of a camera: the sector of the courtyard (by the azimuth of
    its centre) it stands in, as a GPS tag would give (retrieval can be restricted to it)."""
    T = np.asarray(cam_from_world, float)
    c = -T[:, :3].T @ T[:, 3]
    return str(int((np.arctan2(c[1], c[0]) % (2 * np.pi)) // (2 * np.pi / num_areas)) % num_areas)


def generate(root, conf: SyntheticConfig = SyntheticConfig(), num_references: int = 12,
             queries_per_condition: int = 2, camera: CameraRecord = CameraRecord(
                 "PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0)), query_depth: bool = False,
             query_spread: float = 1.0) -> Path:
    """Write a dataset: ``mapping/NNNN.png`` + ``.depth.png`` (uint16 millimetres) along the
    reference path, ``query/<condition>/NNNN.png`` from other viewpoints (with depth too if
    ``query_depth``, for training; ``query_spread`` scales how far they are from the
    references), and ``cameras.json`` (name, COLMAP camera,
    cam_from_world, tags: condition, split, area) for all of them."""
    import json

    import cv2
    root = Path(root)
    scene = SyntheticScene(conf)
    entries = []
    (root / "mapping").mkdir(parents=True, exist_ok=True)
    for i, T in enumerate(scene.reference_poses(num_references)):
        rgb, depth = scene.render(camera, T, "day", seed=conf.seed * 1000 + i)
        name = f"mapping/{i:04d}.png"
        cv2.imwrite(str(root / name), rgb[..., ::-1])
        cv2.imwrite(str(root / f"mapping/{i:04d}.depth.png"), np.clip(depth * 1000, 0, 65534).astype(np.uint16))
        entries.append({"name": name, "camera": [camera.model, camera.width, camera.height, list(camera.params)],
                        "cam_from_world": T.tolist(),
                        "tags": {"condition": "day", "split": "mapping", "area": area(T)}})
    for c, condition in enumerate(CONDITIONS):
        (root / "query" / condition).mkdir(parents=True, exist_ok=True)
        for j, T in enumerate(scene.query_poses(queries_per_condition, seed=conf.seed * 100 + c,
                                                      spread=query_spread)):
            rgb, depth = scene.render(camera, T, condition, seed=conf.seed * 1000 + 500 + 10 * c + j)
            name = f"query/{condition}/{j:04d}.png"
            cv2.imwrite(str(root / name), rgb[..., ::-1])
            if query_depth:
                cv2.imwrite(str(root / name.replace(".png", ".depth.png")),
                            np.clip(depth * 1000, 0, 65534).astype(np.uint16))
            entries.append({"name": name, "camera": [camera.model, camera.width, camera.height,
                                                     list(camera.params)],
                            "cam_from_world": T.tolist(),
                            "tags": {"condition": condition, "split": "query", "area": area(T)}})
    (root / "cameras.json").write_text(json.dumps(
        {"config": conf.__dict__, "generation": _generation(conf, num_references, queries_per_condition, camera,
                                                            query_depth, query_spread),
         "images": entries}, indent=1))
    return root


def _generation(conf: SyntheticConfig, num_references, queries_per_condition, camera: CameraRecord, query_depth,
                query_spread) -> dict:
    """Everything a generated dataset depends on, as stored in its cameras.json."""
    import json
    return json.loads(json.dumps({"config": dict(conf.__dict__), "num_references": num_references,
                                  "queries_per_condition": queries_per_condition, "camera": camera.to_json(),
                                  "query_depth": query_depth, "query_spread": query_spread}))


def ensure_generated(root, conf: SyntheticConfig = SyntheticConfig(), num_references: int = 12,
                     queries_per_condition: int = 2, camera: CameraRecord = CameraRecord(
                         "PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0)), query_depth: bool = False,
                     query_spread: float = 1.0) -> Path:
    """The dataset of these settings at ``root``: reused when the one there was generated with
    the same settings, generated anew (replacing it) otherwise."""
    import json
    import shutil
    root = Path(root)
    wanted = _generation(conf, num_references, queries_per_condition, camera, query_depth, query_spread)
    meta = root / "cameras.json"
    if meta.is_file():
        try:
            if json.loads(meta.read_text()).get("generation") == wanted:
                return root
        except ValueError:
            pass
        logger.info("%s was generated with other settings: generating it again.", root)
        meta.unlink()
        for sub in ("mapping", "query"):
            shutil.rmtree(root / sub, ignore_errors=True)
    return generate(root, conf, num_references, queries_per_condition, camera, query_depth, query_spread)


def read_views(root) -> List[ImageRecord]:
    """Every view of a generated dataset as an ImageRecord (tags: condition, split, area),
    with its depth map where one was written."""
    import json
    root = Path(root)
    views = []
    for e in json.loads((root / "cameras.json").read_text())["images"]:
        model, w, h, params = e["camera"]
        depth = root / e["name"].replace(".png", ".depth.png")
        views.append(ImageRecord(e["name"], root / e["name"], CameraRecord(model, int(w), int(h), tuple(params)),
                                 np.asarray(e["cam_from_world"], float), dict(e["tags"]),
                                 depth_path=depth if depth.is_file() else None, depth_scale=1e-3))
    return views


def read_synthetic(root):
    """(mapping ImageRecords with depth, QueryRecords with ground truth) of a generated dataset."""
    from pipeline.queries import QueryRecord
    views = read_views(root)
    mapping = [v for v in views if v.tags["split"] == "mapping"]
    queries = [QueryRecord(v.name, v.path, v.camera, dict(v.tags), v.cam_from_world)
               for v in views if v.tags["split"] != "mapping"]
    return mapping, queries
