import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pixloc.geometry import COLMAP_MODELS, Camera
from tests.helpers import BATCH_SHAPES, jacobian

# Realistic parameters per COLMAP model (COLMAP convention), mild distortion.
PARAMS = {
    "SIMPLE_PINHOLE": [500.0, 320.0, 240.0],
    "PINHOLE": [500.0, 480.0, 320.0, 240.0],
    "SIMPLE_RADIAL": [500.0, 320.0, 240.0, -0.05],
    "RADIAL": [500.0, 320.0, 240.0, -0.05, 0.01],
    "OPENCV": [500.0, 480.0, 320.0, 240.0, 0.05, -0.02, 0.001, -0.002],
    "FULL_OPENCV": [500.0, 480.0, 320.0, 240.0, 0.05, -0.02, 0.001, -0.002, 0.003, 0.01, -0.005, 0.001],
    "OPENCV_FISHEYE": [300.0, 300.0, 320.0, 240.0, 0.1, -0.02, 0.005, -0.001],
}
MODELS = sorted(COLMAP_MODELS)


def make_camera(model, shape=()) -> Camera:
    """A float64 camera of ``model`` with batch shape ``shape``."""
    cam = Camera.from_colmap(model, 640, 480, PARAMS[model], dtype=torch.float64)
    return cam.reshape(1).expand(*shape) if shape else cam


def points_in_image(cam: Camera, n=50, seed=0, margin=20.0):
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(*cam.shape, n, 2, generator=g, dtype=cam.dtype)
    return margin + u * (cam.size[..., None, :] - 1 - 2 * margin)


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_project_unproject_round_trip(model, shape):
    cam = make_camera(model, shape)
    p2d = points_in_image(cam)
    rays = cam.image2cam(p2d)
    depth = torch.rand(rays.shape[:-1] + (1,), dtype=torch.float64) * 10 + 0.5
    p2d_back, valid = cam.cam2image(rays * depth)
    assert p2d_back.shape == shape + (50, 2) and valid.shape == shape + (50,)
    assert valid.all()
    torch.testing.assert_close(p2d_back, p2d, atol=1e-8, rtol=0)


@pytest.mark.parametrize("model", MODELS)
def test_colmap_principal_point_convention(model):
    cam = Camera.from_colmap(model, 640, 480, PARAMS[model])
    # The principal point of COLMAP (pixel-corner origin) is at c - 0.5 here.
    assert cam.c.tolist() == [319.5, 239.5]
    p2d, valid = cam.cam2image(torch.tensor([[0.0, 0.0, 2.0]]))
    assert valid.all() and p2d.tolist() == [[319.5, 239.5]]


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_J_cam2image_matches_autograd(model, shape):
    cam = make_camera(model, shape)
    p3d = cam.image2cam(points_in_image(cam, n=20, seed=1)) * 3.0
    J = cam.J_cam2image(p3d)
    J_auto = jacobian(lambda p: cam.cam2image(p)[0], p3d)
    assert J.shape == shape + (20, 2, 3)
    torch.testing.assert_close(J, J_auto)


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_cam2image_with_J_is_cam2image_and_its_jacobian(model, shape):
    """The LM's projection and Jacobian at once: the same pixels and validity as ``cam2image`` for points
    in view, behind the camera and outside it; in view, the Jacobian of ``cam2image`` (autograd); behind
    the camera, that of the clamped depth, finite."""
    cam = make_camera(model, shape)
    p3d = cam.image2cam(points_in_image(cam, n=30, seed=2, margin=-100.0)) * 3.0
    p3d[..., :5, 2] *= -1  # behind the camera
    p2d, valid, J = cam.cam2image_with_J(p3d)
    p2d_ref, valid_ref = cam.cam2image(p3d)
    assert torch.equal(p2d, p2d_ref) and torch.equal(valid, valid_ref)
    assert 0 < valid.sum() < valid.numel() and torch.isfinite(J).all()
    front = p3d[..., 5:, :]
    torch.testing.assert_close(J[..., 5:, :, :], jacobian(lambda p: cam.cam2image(p)[0], front))


@pytest.mark.parametrize("model", MODELS)
def test_J_distort_matches_autograd_near_the_axis(model):
    cam = Camera.from_colmap(model, 640, 480, PARAMS[model], dtype=torch.float64)
    p = torch.tensor([[0.0, 0.0], [1e-5, -2e-5], [0.3, -0.2], [-0.5, 0.4]], dtype=torch.float64)
    torch.testing.assert_close(cam.J_distort(p), jacobian(lambda x: cam.distort(x)[0], p))


def test_radial_validity_follows_the_official_inflection_rule():
    # Official PixLoc limits r^2 to |1 / (3 k1)| when k2 <= 0 and k1 > 0, and to
    # the root (sqrt(9 k1^2 - 20 k2) - 3 k1) / (10 k2) of 1 + 3 k1 r^2 + 5 k2 r^4
    # when k2 > 0 and 9 k1^2 > 20 k2 (the larger root when k1 < 0).
    k1 = 0.1
    cam = Camera.from_colmap("SIMPLE_RADIAL", 640, 480, [500.0, 320.0, 240.0, k1])
    limit = (1 / (3 * k1)) ** 0.5
    _, valid = cam.distort(torch.tensor([[limit * 0.99, 0.0], [limit * 1.01, 0.0]]))
    assert valid.tolist() == [True, False]
    k1, k2 = -0.5, 0.05
    cam = Camera.from_colmap("RADIAL", 640, 480, [500.0, 320.0, 240.0, k1, k2])
    r2 = ((9 * k1 ** 2 - 20 * k2) ** 0.5 - 3 * k1) / (10 * k2)
    _, valid = cam.distort(torch.tensor([[(r2 * 0.99) ** 0.5, 0.0], [(r2 * 1.01) ** 0.5, 0.0]]))
    assert valid.tolist() == [True, False]
    # No limit otherwise (k1 < 0, k2 = 0), as in the official code.
    cam = Camera.from_colmap("SIMPLE_RADIAL", 640, 480, [500.0, 320.0, 240.0, -0.1])
    assert cam.distort(torch.tensor([[5.0, 0.0]]))[1].all()


def test_points_behind_or_outside_are_invalid():
    cam = Camera.from_colmap("PINHOLE", 640, 480, PARAMS["PINHOLE"])
    _, valid = cam.cam2image(torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 1e-4], [10.0, 0.0, 1.0], [0.1, 0.1, 1.0]]))
    assert valid.tolist() == [False, False, False, True]


@settings(max_examples=30, deadline=None)
@given(s=st.floats(0.1, 4.0), x=st.floats(0, 639), y=st.floats(0, 479))
def test_scale_maps_pixels_like_a_resize(s, x, y):
    cam = Camera.from_colmap("OPENCV", 640, 480, PARAMS["OPENCV"], dtype=torch.float64)
    ray = cam.image2cam(torch.tensor([[x, y]], dtype=torch.float64))
    p_scaled, _ = cam.scale(s).cam2image(ray)
    # A resize by s maps pixel centres as (p + 0.5) s - 0.5.
    torch.testing.assert_close(p_scaled, (torch.tensor([[x, y]], dtype=torch.float64) + 0.5) * s - 0.5)
    assert cam.scale(s).size.tolist() == pytest.approx([640 * s, 480 * s])


def test_crop_shifts_the_principal_point():
    cam = Camera.from_colmap("PINHOLE", 640, 480, PARAMS["PINHOLE"])
    crop = cam.crop((100, 50), (200, 100))
    p3d = torch.tensor([[0.1, -0.05, 2.0]])
    torch.testing.assert_close(crop.cam2image(p3d)[0], cam.cam2image(p3d)[0] - torch.tensor([100.0, 50.0]))
    assert crop.size.tolist() == [200, 100]


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="Unsupported camera model 'THIN_PRISM_FISHEYE'"):
        Camera.from_colmap("THIN_PRISM_FISHEYE", 640, 480, [1.0] * 16)
    with pytest.raises(ValueError, match="OPENCV has 8 parameters"):
        Camera.from_colmap("OPENCV", 640, 480, [1.0, 2.0])
    with pytest.raises(ValueError, match="infer the camera model from 7"):
        Camera(torch.zeros(7))
    with pytest.raises(ValueError, match="different distortion models"):
        Camera.stack([Camera.from_colmap("OPENCV", 1, 1, PARAMS["OPENCV"]),
                      Camera.from_colmap("OPENCV_FISHEYE", 1, 1, PARAMS["OPENCV_FISHEYE"])])
