import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pixloc.geometry import Pose, pose_error
from pixloc.geometry import lie
from tests.helpers import BATCH_SHAPES


def random_pose(shape, dtype=torch.float64, seed=0, max_angle=math.pi):
    g = torch.Generator().manual_seed(seed)
    axis = torch.nn.functional.normalize(torch.randn(*shape, 3, generator=g, dtype=dtype), dim=-1)
    angle = torch.rand(*shape, 1, generator=g, dtype=dtype) * max_angle
    t = torch.randn(*shape, 3, generator=g, dtype=dtype) * 3
    return Pose.from_Rt(lie.so3_exp(axis * angle), t)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_inverse_and_composition(shape, device):
    T = random_pose(shape).to(device)
    eye = (T @ T.inv()).matrix()
    assert eye.shape == shape + (4, 4)
    torch.testing.assert_close(eye, torch.eye(4, dtype=eye.dtype, device=device).expand_as(eye))
    p = torch.randn(*shape, 7, 3, dtype=torch.float64, device=device)
    U = random_pose(shape, seed=1).to(device)
    torch.testing.assert_close((U @ T).transform(p), U.transform(T.transform(p)))
    torch.testing.assert_close(T.inv().transform(T.transform(p)), p)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_exp_log_round_trip(shape, device):
    T = random_pose(shape, max_angle=3.1).to(device)
    torch.testing.assert_close(Pose.exp(T.log()).data, T.data)
    xi = torch.randn(*shape, 6, dtype=torch.float64, device=device) * 0.5
    torch.testing.assert_close(Pose.exp(xi).log(), xi)


@settings(max_examples=50, deadline=None)
@given(angle=st.floats(0, math.pi - 1e-9), seed=st.integers(0, 2**16))
def test_so3_log_inverts_exp_over_all_angles(angle, seed):
    g = torch.Generator().manual_seed(seed)
    axis = torch.nn.functional.normalize(torch.randn(3, generator=g, dtype=torch.float64), dim=-1)
    w = axis * angle
    R = lie.so3_exp(w)
    torch.testing.assert_close(lie.so3_exp(lie.so3_log(R)), R, atol=1e-9, rtol=0)
    assert abs(float(lie.rotation_angle(R)) - angle) < 1e-9


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_quaternion_round_trip(shape):
    T = random_pose(shape)
    q = T.qvec
    assert q.shape == shape + (4,)
    assert (q[..., 0] >= 0).all()
    torch.testing.assert_close(Pose.from_qvec(q, T.t).data, T.data)


def test_quaternion_is_colmap_order():
    # 90 degrees about z: COLMAP qvec (w, x, y, z) = (cos 45, 0, 0, sin 45).
    q = torch.tensor([math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)], dtype=torch.float64)
    R = Pose.from_qvec(q, torch.zeros(3, dtype=torch.float64)).R
    torch.testing.assert_close(R @ torch.tensor([1.0, 0, 0], dtype=torch.float64),
                               torch.tensor([0.0, 1, 0], dtype=torch.float64))


def test_magnitude_is_stable_for_tiny_rotations():
    angle = 1e-6  # radians: acos((trace - 1) / 2) returns 0 in float32
    T = Pose.from_aa(torch.tensor([0.0, 0.0, angle]), torch.tensor([0.0, 3.0, 4.0]))
    dR, dt = T.magnitude()
    assert float(dR) == pytest.approx(math.degrees(angle), rel=1e-3)
    assert float(dt) == pytest.approx(5.0)


def test_pose_error_is_centre_distance():
    T = random_pose(())
    moved = Pose.from_Rt(T.R, T.t + T.R @ torch.tensor([0.0, 0.0, -0.5], dtype=torch.float64))
    dR, dt = pose_error(moved, T)
    assert float(dR) == pytest.approx(0.0, abs=1e-6)
    assert float(dt) == pytest.approx(0.5)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_J_transform_matches_autograd(shape):
    T = random_pose(shape)
    p = torch.randn(*shape, 6, 3, dtype=torch.float64)

    def transformed(delta):  # delta: (..., 6) left update (dt, dw) of T
        dT = Pose.from_Rt(lie.so3_exp(delta[..., 3:]), delta[..., :3])
        return (dT @ T).transform(p)

    delta0 = torch.zeros(*shape, 6, dtype=torch.float64, requires_grad=True)
    J_auto = torch.stack([torch.autograd.grad(transformed(delta0)[..., k].sum(), delta0, retain_graph=True)[0]
                          for k in range(3)], -2)  # sum over points would mix them: check per point below
    J = T.J_transform(T.transform(p))
    assert J.shape == shape + (6, 3, 6)
    torch.testing.assert_close(J.sum(-3), J_auto)
    # per point
    for n in range(p.shape[-2]):
        Jn = torch.autograd.functional.jacobian(lambda d: transformed(d)[..., n, :], delta0.detach())
        if shape:
            Jn = torch.stack([Jn[i, :, i] for i in range(shape[0])])
        torch.testing.assert_close(J[..., n, :, :], Jn)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_J_left_is_the_product_with_J_transform_and_differentiable(shape):
    T = random_pose(shape)
    p = T.transform(torch.randn(*shape, 6, 3, dtype=torch.float64))
    J = torch.randn(*shape, 6, 2, 3, dtype=torch.float64, requires_grad=True)
    torch.testing.assert_close(Pose.J_left(J, p), J @ T.J_transform(p))
    torch.autograd.gradcheck(lambda j: Pose.J_left(j, p), (J,))


def test_exp_and_log_are_differentiable_at_zero():
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    torch.autograd.gradcheck(lambda x: Pose.exp(x).data, (xi,))
    w = (torch.randn(3, dtype=torch.float64) * 0.3).requires_grad_(True)
    torch.autograd.gradcheck(lambda x: lie.so3_log(lie.so3_exp(x)), (w,))


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="12 values"):
        Pose(torch.zeros(3, 11))
    with pytest.raises(ValueError, match=r"R \(\.\.\., 3, 3\)"):
        Pose.from_Rt(torch.eye(4), torch.zeros(3))
    with pytest.raises(TypeError, match="floating-point"):
        Pose(torch.zeros(12, dtype=torch.long))
    with pytest.raises(ValueError, match=r"\(\.\.\., N, 3\)"):
        Pose.identity(2).transform(torch.zeros(2, 5, 2))
    assert not bool(Pose(torch.full((12,), float("nan"))).isfinite())


def test_from_matrix_and_to_matrix_are_the_numpy_seam():
    import numpy as np
    rng = np.random.default_rng(0)
    T = Pose.from_aa(torch.tensor(rng.normal(size=(5, 3))), torch.tensor(rng.normal(size=(5, 3)))).double()
    M = T.to_matrix()
    assert M.shape == (5, 3, 4) and M.dtype == np.float64
    back = Pose.from_matrix(M)
    torch.testing.assert_close(back._data, T._data)
    noisy = M[0].copy()
    noisy[:, :3] += 1e-4 * rng.normal(size=(3, 3))  # float32 LM updates leave R slightly off SO(3)
    R = Pose.from_matrix(noisy).to_matrix(orthonormal=True)[:, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) > 0
