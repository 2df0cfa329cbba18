"""A generated city for scale tests and benchmarks: a seeded grid of blocks with streets between
them, rendered like the courtyard of ``pipeline.data.synthetic`` (same materials, lighting and
conditions), with references along every street and area tags per block side."""

from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Tuple

import numpy as np

from pipeline.data.synthetic import (
    BRICK,
    CONDITIONS,
    FOLIAGE,
    GROUND,
    PLASTER,
    POLE,
    TRUNK,
    SyntheticScene,
    load_texture,
    box_mesh,
    look_at,
)
from pipeline.scene import CameraRecord

TEXTURE_SIDE = 768  # pixels: photos are shrunk to this before they texture facades (memory)


@dataclass(frozen=True)
class CityConfig:
    """A seeded grid of city blocks with streets between them: ``blocks`` (nx, ny) blocks of
    ``block_size`` metres, streets ``street`` metres wide. Buildings line each block's four
    sides (varied widths, heights, materials), poles, trees and street lamps line the streets.
    References stand along every street every ``spacing`` metres, one camera facing each side;
    each image's ``area`` tag is the block side it looks at (``bx-by-side``, side n/e/s/w: about
    what a GPS tag tells), and ``block`` the block (``bx-by``). ``detail``: fine stains on every
    surface (0: none, the courtyard's look), for local features (SIFT triangulation, S4).
    ``textures``: photos that cover every building's facades instead of procedural plaster and
    brick, ``texture_scale`` metres per photo width."""

    seed: int = 0
    blocks: Tuple[int, int] = (3, 3)
    block_size: float = 24.0
    street: float = 10.0
    spacing: float = 4.0
    detail: float = 0.0
    textures: Tuple[str, ...] = ()
    texture_scale: float = 8.0


class SyntheticCity(SyntheticScene):
    """The city of a CityConfig (renders like the courtyard: ``render``)."""

    photo_every_facade = True  # with textures, every building's facades are photos

    def __init__(self, conf: CityConfig = CityConfig()):
        rng = np.random.default_rng(conf.seed)
        self.conf = conf
        self.textures = [load_texture(p, max_side=TEXTURE_SIDE) for p in conf.textures]
        nx, ny = conf.blocks
        pitch = conf.block_size + conf.street
        self.pitch = pitch
        W, H = nx * pitch + conf.street, ny * pitch + conf.street
        parts: List[Tuple[np.ndarray, np.ndarray, int]] = [
            (np.array([[0, 0, 0], [W, 0, 0], [W, H, 0], [0, H, 0]], float), np.array([[0, 1, 2], [0, 2, 3]]), GROUND)]
        for bx in range(nx):
            for by in range(ny):
                x0, y0 = conf.street + bx * pitch, conf.street + by * pitch
                B = conf.block_size
                for side in range(4):  # buildings along each side, their facades on the street
                    s = 0.0
                    while s < B - 1:
                        w = min(rng.uniform(5, 10), B - s)
                        h, d = rng.uniform(6, 18), rng.uniform(5, 8)
                        u = s + w / 2
                        centre, size = {0: ((x0 + u, y0 + d / 2), (w - 0.3, d)),
                                        1: ((x0 + B - d / 2, y0 + u), (d, w - 0.3)),
                                        2: ((x0 + B - u, y0 + B - d / 2), (w - 0.3, d)),
                                        3: ((x0 + d / 2, y0 + B - u), (d, w - 0.3))}[side]
                        material = PLASTER if rng.random() < 0.6 else BRICK
                        parts.append((*box_mesh((*centre, h / 2), (*size, h)), material))
                        s += w
        lamps = []
        for k in range(nx + 1):  # street furniture along the streets running in y, then in x
            for j in range(int(H // 12)):
                x = k * pitch + conf.street * (0.15 if j % 2 else 0.85)
                y = 6 + 12 * j + rng.uniform(-2, 2)
                kind = rng.random()
                if kind < 0.4:
                    parts.append((*box_mesh((x, y, 2.5), (0.15, 0.15, 5.0)), POLE))
                    lamps.append([x, y, 4.5])
                elif kind < 0.6:
                    parts.append((*box_mesh((x, y, 1.5), (0.4, 0.4, 3.0)), TRUNK))
                    parts.append((*box_mesh((x, y, 4.0), (2.5, 2.5, 2.5)), FOLIAGE))
        for k in range(ny + 1):
            for j in range(int(W // 12)):
                y = k * pitch + conf.street * (0.15 if j % 2 else 0.85)
                x = 6 + 12 * j + rng.uniform(-2, 2)
                if rng.random() < 0.4:
                    parts.append((*box_mesh((x, y, 2.5), (0.15, 0.15, 5.0)), POLE))
                    lamps.append([x, y, 4.5])
        self.parts = parts
        self.lamps = np.array(lamps).reshape(-1, 3)

    def _street_views(self, spacing: float):
        """(eye, facing direction, block looked at) along the middle of every street."""
        c = self.conf
        nx, ny = c.blocks
        views = []
        for k in range(nx + 1):  # streets along y at x = k * pitch + street / 2
            x = k * self.pitch + c.street / 2
            for y in np.arange(c.street / 2 + spacing / 2, ny * self.pitch + c.street / 2, spacing):
                by = int((y - c.street) // self.pitch)
                if not 0 <= (y - c.street) % self.pitch <= c.block_size:  # a crossing: no facade ahead
                    continue
                for dx, bx, side in ((-1.0, k - 1, "e"), (1.0, k, "w")):
                    if 0 <= bx < nx and 0 <= by < ny:
                        views.append((np.array([x, y]), np.array([dx, 0.0]), f"{bx}-{by}-{side}"))
        for k in range(ny + 1):
            y = k * self.pitch + c.street / 2
            for x in np.arange(c.street / 2 + spacing / 2, nx * self.pitch + c.street / 2, spacing):
                bx = int((x - c.street) // self.pitch)
                if not 0 <= (x - c.street) % self.pitch <= c.block_size:
                    continue
                for dy, by, side in ((-1.0, k - 1, "n"), (1.0, k, "s")):
                    if 0 <= bx < nx and 0 <= by < ny:
                        views.append((np.array([x, y]), np.array([0.0, dy]), f"{bx}-{by}-{side}"))
        return views

    def reference_views(self, height: float = 1.6) -> List[Tuple[np.ndarray, str]]:
        """(cam_from_world, area) of the references: along every street, facing each block side,
        looking slightly along the street so that neighbours overlap."""
        out = []
        for k, (eye, facing, block) in enumerate(self._street_views(self.conf.spacing)):
            along = np.array([facing[1], -facing[0]]) * (0.3 if k % 2 else -0.3)
            e = np.array([*(eye - facing * 0.3 * self.conf.street), height])  # across the street
            out.append((look_at(e, e + np.array([*(facing + along), 0.15])), block))
        return out

    def query_views(self, n: int, seed: int, spread: float = 1.0, block: Optional[str] = None,
                    near_references: bool = False) -> List[Tuple[np.ndarray, str]]:
        """Other viewpoints on the streets: off the middle line (spread x 3 m), heights 1.3-2.2 m,
        headings up to spread x 0.4 rad off the facade normal; only around ``block`` (``bx-by``)
        if given (the same queries in cities of any size: block 0-0 is built first in each).
        ``near_references``: instead, offsets like those between neighbouring mapping views,
        around a random reference (``near_reference_views``)."""
        if near_references:
            return self.near_reference_views(n, seed, spread, block)
        rng = np.random.default_rng(seed)
        views = [v for v in self._street_views(1.0) if block is None or v[2].rsplit("-", 1)[0] == block]
        out = []
        for k in rng.integers(0, len(views), n):
            eye, facing, block = views[k]
            side = np.array([facing[1], -facing[0]])
            e = np.array([*(eye - facing * spread * rng.uniform(0, 3.5) + side * rng.uniform(-0.5, 0.5)),
                          rng.uniform(1.3, 2.2)])
            d = _turned(facing, spread * rng.uniform(-0.4, 0.4))
            out.append((look_at(e, e + np.array([*d, rng.uniform(0.05, 0.2)])), block))
        return out

    def near_reference_views(self, n: int, seed: int, spread: float = 1.0,
                             block: Optional[str] = None) -> List[Tuple[np.ndarray, str]]:
        """Viewpoints around random references (of ``block`` if given): moved spread x 2 m along
        the street and spread x [-1.5, 2.5] m towards the facade, heights 1.3-2.2 m, turned up to
        spread x 0.4 rad; what the demo's courtyard draws around its reference circle."""
        rng = np.random.default_rng(seed)
        refs = [(T, b) for T, b in self.reference_views() if block is None or b.rsplit("-", 1)[0] == block]
        out = []
        for k in rng.integers(0, len(refs), n):
            T, side = refs[k]
            R, t = T[:, :3], T[:, 3]
            centre, forward = -R.T @ t, R[2]
            facing = forward[:2] / np.linalg.norm(forward[:2])
            normal = _facade_normal(facing)
            along = np.array([normal[1], -normal[0]])
            e = centre[:2] + along * spread * rng.uniform(-2, 2) + normal * spread * rng.uniform(-1.5, 2.5)
            d = _turned(facing, spread * rng.uniform(-0.4, 0.4))
            eye = np.array([*e, rng.uniform(1.3, 2.2)])
            out.append((look_at(eye, eye + np.array([*d, rng.uniform(0.05, 0.2)])), side))
        return out


def _facade_normal(facing: np.ndarray) -> np.ndarray:
    """The street axis direction a camera faces (towards its facade), from its heading."""
    k = int(np.argmax(np.abs(facing)))
    axis = np.zeros(2)
    axis[k] = np.sign(facing[k])
    return axis


def _turned(d: np.ndarray, a: float) -> np.ndarray:
    """The 2D direction ``d`` turned by ``a`` radians."""
    return np.array([d[0] * np.cos(a) - d[1] * np.sin(a), d[0] * np.sin(a) + d[1] * np.cos(a)])


def generate_city(root, conf: CityConfig = CityConfig(), queries_per_condition: int = 2,
                  camera: CameraRecord = CameraRecord("PINHOLE", 160, 120, (125.0, 125.0, 80.0, 60.0)),
                  query_spread: float = 1.0, query_block: Optional[str] = None, progress=None,
                  queries_near_references: bool = False) -> Path:
    """Write a city dataset in the format of ``generate`` (``read_synthetic`` reads it);
    ``area`` tags are block sides, ``block`` tags blocks; queries only around ``query_block``
    if given, around the references if ``queries_near_references`` (``query_views``).
    Regenerated only when its settings change (``cameras.json``)."""
    import json

    import cv2
    root = Path(root)
    wanted = json.loads(json.dumps({"city": dict(conf.__dict__), "queries_per_condition": queries_per_condition,
                                    "camera": camera.to_json(), "query_spread": query_spread,
                                    "query_block": query_block, **({"queries_near_references": True}
                                                                   if queries_near_references else {})}))
    meta = root / "cameras.json"
    if meta.is_file() and json.loads(meta.read_text()).get("generation") == wanted:
        return root
    city = SyntheticCity(conf)
    views = [("mapping", "day", i, T, block) for i, (T, block) in enumerate(city.reference_views())]
    for c, condition in enumerate(CONDITIONS):
        views += [("query", condition, j, T, block) for j, (T, block) in
                  enumerate(city.query_views(queries_per_condition, conf.seed * 100 + c, query_spread,
                                             query_block, queries_near_references))]
    entries = []
    for k, (split, condition, j, T, block) in enumerate(views):
        rgb, depth = city.render(camera, T, condition, seed=conf.seed * 100003 + k)
        name = f"mapping/{j:05d}.png" if split == "mapping" else f"query/{condition}/{j:05d}.png"
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(root / name), rgb[..., ::-1])
        if split == "mapping":
            cv2.imwrite(str(root / name.replace(".png", ".depth.png")),
                        np.clip(depth * 1000, 0, 65534).astype(np.uint16))
        entries.append({"name": name, "camera": [camera.model, camera.width, camera.height, list(camera.params)],
                        "cam_from_world": T.tolist(), "tags": {"condition": condition, "split": split, "area": block,
                                                               "block": block.rsplit("-", 1)[0]}})
        if progress:
            progress(k + 1, len(views))
    meta.write_text(json.dumps({"config": {"city": dict(conf.__dict__)}, "generation": wanted, "images": entries}))
    return root
