"""Pins of the geometry convention: identity warp, known shifts, batching, gradients, points behind the camera."""

import pytest
import torch
from scipy.spatial.transform import Rotation

from nvs.core.geometry import about_pivot, inverse_warp, invert_pose, pose_matrix, scale_intrinsics


def _K(B, f=1.0, cx=4.5, cy=3.5, dtype=torch.float32):
    return torch.tensor([[f, 0, cx], [0, f, cy], [0, 0, 1.0]], dtype=dtype).expand(B, 3, 3).clone()


def _T(B, R=None, t=(0.0, 0.0, 0.0), dtype=torch.float32):
    R = torch.eye(3, dtype=dtype) if R is None else torch.as_tensor(R, dtype=dtype)
    return pose_matrix(R.expand(B, 3, 3), torch.tensor(t, dtype=dtype).expand(B, 3))


def test_identity_pose_is_identity_warp():
    B, H, W = 2, 8, 10
    src = torch.rand(B, 3, H, W)
    depth = torch.rand(B, 1, H, W) + 0.5
    warped, valid = inverse_warp(src, depth, _K(B, f=5.0), _T(B))
    assert valid.min() == 1.0
    torch.testing.assert_close(warped, src, atol=1e-5, rtol=0)


def test_known_translation_shifts_by_known_pixels():
    # Source points move +1 along x into the target camera; at depth 1 and f = 1... use f = 2: shift = f*tx/z = 2 px.
    B, H, W = 1, 6, 12
    src = torch.arange(W, dtype=torch.float32).expand(B, 1, H, W).clone()
    warped, valid = inverse_warp(src, torch.ones(B, 1, H, W), _K(B, f=2.0, cx=5.5, cy=2.5), _T(B, t=(1.0, 0, 0)))
    # target pixel u sees source pixel u - 2
    torch.testing.assert_close(warped[..., 2:], src[..., :-2], atol=1e-5, rtol=0)
    assert valid[..., :2].sum() == 0 and valid[..., 2:].min() == 1


def test_subpixel_shift_interpolates_bilinearly():
    B, H, W = 1, 4, 8
    src = torch.arange(W, dtype=torch.float32).expand(B, 1, H, W).clone()
    warped, valid = inverse_warp(src, torch.full((B, 1, H, W), 4.0), _K(B, f=2.0), _T(B, t=(1.0, 0, 0)))
    # shift f*tx/z = 0.5 px: value at u is u - 0.5 wherever valid
    m = valid[0, 0] > 0
    torch.testing.assert_close(warped[0, 0][m], (src[0, 0] - 0.5)[m], atol=1e-5, rtol=0)


def test_batched_equals_per_sample():
    torch.manual_seed(0)
    B, H, W = 3, 9, 7
    src = torch.rand(B, 4, H, W)
    depth = torch.rand(B, 1, H, W) * 2 + 1
    R = torch.from_numpy(Rotation.from_rotvec(Rotation.random(B, random_state=1).as_rotvec() * 0.1).as_matrix()).float()
    T = pose_matrix(R, torch.randn(B, 3) * 0.1)
    K = _K(B, f=6.0)
    warped, valid = inverse_warp(src, depth, K, T)
    for i in range(B):
        w_i, v_i = inverse_warp(src[i:i + 1], depth[i:i + 1], K[i:i + 1], T[i:i + 1])
        torch.testing.assert_close(warped[i:i + 1], w_i)
        torch.testing.assert_close(valid[i:i + 1], v_i)


def test_gradcheck_float64():
    torch.manual_seed(0)
    B, H, W = 1, 5, 6
    src = torch.rand(B, 2, H, W, dtype=torch.float64, requires_grad=True)
    depth = (torch.rand(B, 1, H, W, dtype=torch.float64) + 1.5).requires_grad_(True)
    T = _T(B, R=Rotation.from_euler("y", 3, degrees=True).as_matrix(), t=(0.05, 0.02, 0.0), dtype=torch.float64)
    K = _K(B, f=4.0, cx=2.5, cy=2.0, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda s, d: inverse_warp(s, d, K, T)[0], (src, depth), eps=1e-6, atol=1e-5)


def test_points_behind_camera_are_invalid_and_finite():
    B, H, W = 1, 6, 6
    src = torch.rand(B, 3, H, W)
    depth = torch.ones(B, 1, H, W, requires_grad=True)
    T = _T(B, t=(0.0, 0.0, 5.0))  # source camera 5 units in front: every point is behind it
    warped, valid = inverse_warp(src, depth, _K(B, f=3.0, cx=2.5, cy=2.5), T)
    assert valid.sum() == 0
    assert torch.isfinite(warped).all() and warped.abs().sum() == 0
    warped.sum().backward()
    assert torch.isfinite(depth.grad).all()
    # Non-positive depth is invalid too.
    _, valid0 = inverse_warp(src, torch.zeros(B, 1, H, W), _K(B), _T(B))
    assert valid0.sum() == 0


def test_scale_intrinsics_follows_pixel_centres():
    K = torch.tensor([[480.0, 0, 128.0], [0, 480.0, 128.0], [0, 0, 1]])
    K64 = scale_intrinsics(K, 0.25)
    assert K64[0, 0] == 120.0 and K64[0, 2] == pytest.approx(31.625)
    torch.testing.assert_close(scale_intrinsics(K64, 4.0), K)


def test_invert_pose_and_pivot():
    R = torch.from_numpy(Rotation.from_euler("xyz", [10, 30, -5], degrees=True).as_matrix()).float()[None]
    c = torch.tensor([[0.0, 0.0, 2.0]])
    T = pose_matrix(R, c - (R @ c[..., None])[..., 0])
    torch.testing.assert_close(invert_pose(T) @ T, torch.eye(4)[None], atol=1e-6, rtol=0)
    # An object-centric pose about c is a pure rotation in pivot-centred coordinates.
    P = about_pivot(T, c)
    torch.testing.assert_close(P[0, :3, 3], torch.zeros(3), atol=1e-6, rtol=0)
    torch.testing.assert_close(P[0, :3, :3], R[0])


def test_shape_errors_are_clear():
    with pytest.raises(ValueError, match="K must have shape"):
        inverse_warp(torch.rand(1, 3, 4, 4), torch.ones(1, 1, 4, 4), torch.eye(4)[None], _T(1))
