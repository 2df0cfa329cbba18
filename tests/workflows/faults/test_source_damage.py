"""Fault catalogue, map sources: random damage to the files a user's map comes from (Bundler,
Middlebury, LLFF, transforms.json, OpenSfM, a COLMAP model in binary or text) gives an error that
names the file, or images that are each usable; never another exception, a hang, or a model read
short without a word."""

import json
import random
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.mapping.readers.colmap import read_colmap
from pipeline.mapping.readers.colmap_files import check_binary_model
from pipeline.scene import SceneError
from pipeline.textfiles import InputError
from pipeline.mapping.readers.sources import posed_images

from .test_random_damage import SETTINGS, damaged

ROOT = Path(__file__).resolve().parents[3]
ODD_JSON = ["x", None, [], {}, -1, 0, float("nan"), float("inf"), 1e300, [1, 2], [[1, 2], [3]], True, "../a.jpg"]


def _posed(kind: str, path: Path, images=None):
    """``posed_images`` of a damaged source: a SceneError or InputError that names ``path``, or images
    that each pass ``ImageRecord.check``."""
    try:
        found, _ = posed_images(kind, path, images)
    except (SceneError, InputError) as e:
        assert str(path) in str(e) or str(path.parent) in str(e), str(e)
        return None
    assert found and all(im.check() is None for im in found)
    return found


def _folder(links: dict) -> Path:
    """A new folder holding symbolic links ``name -> target``."""
    root = Path(tempfile.mkdtemp())
    for name, target in links.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).symlink_to(target)
    return root


@settings(max_examples=80, **SETTINGS)
@given(data=st.data())
def test_bundle_file(shared, data):
    kermit = shared / "data" / "bundler_kermit"
    root = _folder({p.name: p for p in kermit.glob("*.jpg")})
    (root / "results").mkdir()
    path = root / "results" / "bundle.out"
    path.write_bytes(data.draw(damaged((kermit / "results.example" / "bundle.out").read_text())))
    _posed("bundler", path, root)


@settings(max_examples=80, **SETTINGS)
@given(data=st.data())
def test_middlebury_par_file(shared, data):
    temple = shared / "data" / "middlebury" / "templeRing"
    root = _folder({p.name: p for p in temple.glob("*.png")})
    path = root / "templeR_par.txt"
    path.write_bytes(data.draw(damaged((temple / "templeR_par.txt").read_text())))
    _posed("middlebury", root)


@settings(max_examples=60, **SETTINGS)
@given(at=st.floats(0, 1), scale=st.sampled_from([1.0, -1.0, 0.0, 1e300, np.nan]),
       flips=st.lists(st.tuples(st.floats(0, 1), st.integers(0, 255)), max_size=6),
       keep=st.one_of(st.just(1.0), st.floats(0, 1)))
def test_llff_poses_bounds(shared, at, scale, flips, keep):
    beer = shared / "data" / "beer_capture"
    root = _folder({"images": beer / "images"})
    poses = np.load(beer / "poses_bounds.npy")
    poses.flat[int(at * (poses.size - 1))] *= scale  # a value out of range
    np.save(root / "poses_bounds.npy", poses)
    raw = bytearray((root / "poses_bounds.npy").read_bytes())
    for where, value in flips:  # bytes of the header or the numbers
        raw[int(where * (len(raw) - 1))] = value
    (root / "poses_bounds.npy").write_bytes(bytes(raw[:int(keep * len(raw))]))
    _posed("llff", root)


def _json_damage(value, rng: random.Random):
    """``value`` with one to three nodes replaced by a value of another type, or dropped."""
    for _ in range(rng.randint(1, 3)):
        nodes = []

        def walk(v, parent, key):
            nodes.append((parent, key))
            for k in (list(v) if isinstance(v, dict) else range(len(v)) if isinstance(v, list) else ()):
                walk(v[k], v, k)
        walk(value, None, None)
        if len(nodes) < 2:
            break
        parent, key = rng.choice(nodes[1:])
        if rng.random() < 0.3:
            del parent[key]
        else:
            parent[key] = rng.choice(ODD_JSON)
    return value


@pytest.fixture(scope="module")
def transforms_json(shared) -> dict:
    """A transforms.json of six beer_capture photos, made from their LLFF poses (OpenGL axes)."""
    images, _ = posed_images("llff", shared / "data" / "beer_capture")
    frames = []
    for im in images[:6]:
        T = np.eye(4)
        T[:3] = im.cam_from_world
        c2w = np.linalg.inv(T)
        c2w[:3, :3] = c2w[:3, :3] @ np.diag([1.0, -1.0, -1.0])
        frames.append({"file_path": f"images/{im.name}", "transform_matrix": c2w.tolist()})
    f, cx, cy = images[0].camera.params
    return {"fl_x": f, "cx": cx, "cy": cy, "w": images[0].camera.width, "h": images[0].camera.height,
            "k1": 0.01, "frames": frames}


@settings(max_examples=120, **SETTINGS)
@given(data=st.data(), seed=st.integers(0, 2**31), text=st.booleans())
def test_transforms_json(shared, transforms_json, data, seed, text):
    root = _folder({"images": shared / "data" / "beer_capture" / "images"})
    path = root / "transforms.json"
    rng = random.Random(seed)
    if text:  # damage to the text: mostly JSON that no longer parses
        path.write_bytes(data.draw(damaged(json.dumps(transforms_json, indent=1))))
    else:  # damage to the values: JSON of the wrong types and sizes
        path.write_text(json.dumps(_json_damage(json.loads(json.dumps(transforms_json)), rng)))
    _posed("transforms", path)


@settings(max_examples=120, **SETTINGS)
@given(seed=st.integers(0, 2**31))
def test_opensfm_reconstruction(shared, seed):
    berlin = shared / "data" / "opensfm_berlin"
    root = _folder({"images": berlin / "images"})
    path = root / "reconstruction.json"
    value = json.loads((berlin / "reconstruction_example.json").read_text())
    path.write_text(json.dumps(_json_damage(value, random.Random(seed))))
    _posed("opensfm", path)


def colmap_trials(model: str, images: str, trials: int, seed: int) -> None:
    """Random truncations and byte flips of a binary model's files, each read with ``read_colmap``:
    a strict prefix of a file is always refused, naming it; any damage gives a named SceneError or a
    scene. Run in a process of its own by the test below, with a time and memory limit: a hang or a
    runaway allocation of pycolmap's reader would otherwise take the test run down."""
    rng = random.Random(seed)
    for _ in range(trials):
        tmp = Path(tempfile.mkdtemp())
        shutil.copytree(model, tmp / "model")
        path = rng.choice(sorted((tmp / "model").glob("*.bin")))
        path.chmod(0o644)
        raw = bytearray(path.read_bytes())
        cut = rng.random() < 0.5
        if cut:
            raw = raw[:rng.randrange(len(raw))]
        else:
            for _ in range(rng.choice([1, 8])):
                raw[rng.randrange(len(raw))] = rng.randrange(256)
        path.write_bytes(bytes(raw))
        try:
            read_colmap(tmp / "model", images)
            assert not cut, f"{path.name} cut to {len(raw)} bytes was read"
        except SceneError as e:  # a cut file is refused by the check, before pycolmap reads it
            assert str(path if cut else tmp / "model") in str(e), str(e)
        shutil.rmtree(tmp)
    print("done", trials)


def test_colmap_binary_model(shared):
    """The trials above on beer_capture's model, in a process with a time limit: before the files
    were checked, a truncated points3D.bin made pycolmap take 8 GB in 20 s."""
    beer = shared / "data" / "beer_capture"
    code = ("import resource; resource.setrlimit(resource.RLIMIT_AS, (6 << 30, 6 << 30)); "  # a runaway: bad_alloc
            "from tests.workflows.faults.test_source_damage import colmap_trials; "
            f"colmap_trials({str(beer / 'sparse' / '0')!r}, {str(beer / 'images')!r}, 40, 0)")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and "done 40" in out.stdout, out.stderr[-3000:]


def test_binary_model_prefixes_refused(shared, tmp_path):
    """Every strict prefix of each binary file, at 200 cuts, is refused by the check, naming the file."""
    model = shared / "data" / "beer_capture" / "sparse" / "0"
    check_binary_model(model)  # the whole model passes
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        data = (model / name).read_bytes()
        shutil.copytree(model, tmp_path / name)
        path = tmp_path / name / name
        path.chmod(0o644)
        for cut in sorted(set(np.linspace(0, len(data) - 1, 200).astype(int))):
            path.write_bytes(data[:cut])
            with pytest.raises(SceneError, match=str(path)):
                check_binary_model(path.parent)


def test_text_model_cut_at_a_line_end(shared, tmp_path):
    """A text model whose points3D.txt is cut at a line end reads in pycolmap without an error; its
    header's count refuses it (the map would have silently lost the points)."""
    import pycolmap
    rec = pycolmap.Reconstruction(str(shared / "data" / "beer_capture" / "sparse" / "0"))
    (tmp_path / "model").mkdir()
    rec.write_text(str(tmp_path / "model"))
    path = tmp_path / "model" / "points3D.txt"
    text = path.read_text()
    assert read_colmap(tmp_path / "model", shared / "data" / "beer_capture" / "images").points.shape == (4414, 3)
    path.write_text(text[:text.rindex("\n", 0, len(text) // 2) + 1])
    with pytest.raises(SceneError, match=rf"{path}: it holds \d+ points of the 4414 its header names"):
        read_colmap(tmp_path / "model", shared / "data" / "beer_capture" / "images")


@settings(max_examples=25, **SETTINGS)
@given(frame=st.integers(1, 5), keep=st.one_of(st.just(1.0), st.floats(0, 0.99)),
       flips=st.lists(st.tuples(st.floats(0, 1), st.integers(1, 255)), max_size=4))
def test_rgbd_depth_file(shared, frame, keep, flips):
    """A damaged depth map of one RGB-D frame: that frame fails, named with its depth file, and observes
    nothing; the map is made of the others. Before: the whole build stopped, or a depth map decoded in
    part read its missing rows as zero depth."""
    from pipeline.mapping.readers.sources import MapSource, load_scene
    kinect = shared / "data" / "rgbd_slambook" / "kinect_room"
    root = _folder({**{f"color/{p.name}": p for p in (kinect / "color").iterdir()},
                    **{f"depth/{p.name}": p for p in (kinect / "depth").iterdir() if p.stem != str(frame)},
                    "pose.txt": kinect / "pose.txt"})
    raw = bytearray((kinect / "depth" / f"{frame}.pgm").read_bytes())
    for at, xor in flips:
        raw[int(at * (len(raw) - 1))] ^= xor
    path = root / "depth" / f"{frame}.pgm"
    path.write_bytes(bytes(raw[:int(keep * len(raw))]))
    source = MapSource("posetxt", root, intrinsics=(518.0, 519.0, 325.5, 253.5), depth_ext=".pgm",
                       depth_scale=0.001, rgbd_points="frames")
    scene = load_scene(source, root / "work")
    problems = scene.check()
    assert set(problems) <= {frame - 1} and len(scene.points) > 500
    if problems:
        assert str(path) in problems[frame - 1] and frame - 1 not in set(scene.obs_image.tolist())
    else:  # read whole: the flips changed values only (a PGM has no checksum), never its size
        assert (scene.obs_image == frame - 1).sum() > 100


def test_unreadable_images_are_left_out_of_sift_by_name(shared, tmp_path, caplog):
    """SfM and triangulation read their images with the one image reader first: a truncated, empty or
    fake image is left out of SIFT and matching with its reason (before: COLMAP read a truncated JPEG in
    part, and logged 'Image X does not exist' once per pair for one it could not read)."""
    from pipeline.mapping.readers.colmap import images_fingerprint
    from pipeline.mapping.image_pairs import PairsConfig
    from pipeline.mapping.structure import Tasks, build_database
    photos = sorted((shared / "data" / "sacre_coeur" / "mapping").glob("*.jpg"))[:2]
    for p in photos:
        (tmp_path / p.name).symlink_to(p)
    (tmp_path / "cut.jpg").write_bytes(photos[0].read_bytes()[:20000])
    (tmp_path / "zero.jpg").write_bytes(b"")
    (tmp_path / "fake.png").write_bytes(b"GIF89a")
    names = ["cut.jpg", photos[0].name, "zero.jpg", "fake.png", photos[1].name, "missing.jpg"]

    def build(names, work):
        files = {f[0]: f for f in images_fingerprint(tmp_path, names)["images"]}
        return build_database(work / "database.db", tmp_path, names, files, PairsConfig(), Tasks())
    with caplog.at_level("WARNING"):
        kept = build(names, tmp_path / "work")
    assert kept == [photos[0].name, photos[1].name]
    said = caplog.text
    assert "4 of 6 images left out of SIFT and matching" in said
    for name, why in (("cut.jpg", "cannot be decoded"), ("zero.jpg", "is empty"), ("fake.png", "cannot be decoded"),
                      ("missing.jpg", "is missing")):
        assert f"{name}: image file {tmp_path / name} {why}" in said, said
    import pycolmap
    with pycolmap.Database.open(tmp_path / "work" / "database.db") as db:
        assert sorted(im.name for im in db.read_all_images()) == sorted(kept) and db.num_matched_image_pairs() == 1
    with pytest.raises(SceneError, match=r"None of the 2 images .* can be read \(first: zero.jpg"):
        build(["zero.jpg", "fake.png"], tmp_path / "none")
