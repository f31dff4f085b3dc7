"""Camera geometry: thin, documented wrappers over kornia.

Convention (stated once, pinned by tests/test_geometry.py):
    - OpenCV camera: x right, y down, z forward; depth is z along the optical axis.
    - Pixel centres at integer coordinates: pixel (u, v) covers [u-0.5, u+0.5] x [v-0.5, v+0.5].
    - Sampling uses ``grid_sample(align_corners=True)`` on coordinates normalised by (W-1), (H-1), which
      is the exact inverse of that pixel convention: an identity warp reproduces the input exactly.
    - ``T_dst_src`` (B,4,4) maps points expressed in the src camera into the dst camera.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from kornia.geometry.conversions import normalize_pixel_coordinates
from kornia.geometry.depth import depth_to_3d_v2
from kornia.geometry.linalg import transform_points

# Projections this far (in pixels) outside the border still count as inside: round-off of an exact border hit.
BORDER_TOLERANCE = 1e-3
# Points closer than this to the camera plane (in pose units) are treated as behind the camera.
MIN_DEPTH = 1e-6


def _check(cond: bool, msg: str) -> None:
    if not cond:
        raise ValueError(msg)


def scale_intrinsics(K: torch.Tensor, sx: float, sy: float | None = None) -> torch.Tensor:
    """Intrinsics of an image resized by (sx, sy), under the integer pixel-centre convention.

    K (...,3,3) -> (...,3,3). A pixel centre u maps to (u + 0.5)·s - 0.5, so fx' = s·fx and
    cx' = s·(cx + 0.5) - 0.5.
    """
    sy = sx if sy is None else sy
    _check(K.shape[-2:] == (3, 3), f"K must have shape (...,3,3), got {tuple(K.shape)}")
    K = K.clone()
    K[..., 0, 0] = K[..., 0, 0] * sx
    K[..., 0, 1] = K[..., 0, 1] * sx
    K[..., 1, 1] = K[..., 1, 1] * sy
    K[..., 0, 2] = (K[..., 0, 2] + 0.5) * sx - 0.5
    K[..., 1, 2] = (K[..., 1, 2] + 0.5) * sy - 0.5
    return K


def downsample_depth(depth: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Depth (B,1,H,W) -> (B,1,h,w) by area averaging (H/h, W/w integral), matching ``scale_intrinsics``."""
    if depth.shape[-2:] == torch.Size(size):
        return depth
    fh, fw = depth.shape[-2] // size[0], depth.shape[-1] // size[1]
    _check(fh * size[0] == depth.shape[-2] and fw * size[1] == depth.shape[-1],
           f"depth {tuple(depth.shape[-2:])} is not an integer multiple of {size}")
    return F.avg_pool2d(depth, (fh, fw))


def invert_pose(T: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid transforms (B,4,4) -> (B,4,4), exact for [R|t] (uses R^T, not a general inverse)."""
    R, t = T[..., :3, :3], T[..., :3, 3:]
    Rt = R.transpose(-1, -2)
    out = torch.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3:] = -Rt @ t
    out[..., 3, 3] = 1
    return out


def project_to_source(depth_tgt: torch.Tensor, K: torch.Tensor, T_tgt_src: torch.Tensor):
    """Source-pixel coordinates of every target pixel.

    depth_tgt (B,1,H,W), K (B,3,3), T_tgt_src (B,4,4) ->
        uv (B,H,W,2) source pixel coordinates (garbage where invalid, but finite),
        z_src (B,H,W) depth of the point in the source camera,
        in_front (B,H,W) bool: target depth > 0 and source depth > MIN_DEPTH.
    """
    B, _, H, W = depth_tgt.shape
    _check(K.shape == (B, 3, 3), f"K must have shape ({B},3,3), got {tuple(K.shape)}")
    _check(T_tgt_src.shape == (B, 4, 4), f"T_tgt_src must have shape ({B},4,4), got {tuple(T_tgt_src.shape)}")
    # Pixel positions need float32 at least: under bf16 autocast the matmuls below would misplace them by up to
    # ~0.4 px at 64^2 and ~1.6 px at 256^2.
    dtype = torch.promote_types(torch.promote_types(depth_tgt.dtype, K.dtype), torch.float32)
    with torch.autocast(device_type=depth_tgt.device.type, enabled=False):
        return _project(depth_tgt.to(dtype), K.to(dtype), T_tgt_src.to(dtype))


def _project(depth_tgt: torch.Tensor, K: torch.Tensor, T_tgt_src: torch.Tensor):
    B = depth_tgt.shape[0]
    # Non-finite depth is no data, like 0: left in, it would make the gradients w.r.t. K and the pose NaN.
    d = torch.where(torch.isfinite(depth_tgt[:, 0]), depth_tgt[:, 0], torch.zeros_like(depth_tgt[:, 0]))
    pts_tgt = depth_to_3d_v2(d, K)  # (B,H,W,3), pixel centres at integer coordinates
    T_src_tgt = invert_pose(T_tgt_src)
    pts_src = transform_points(T_src_tgt[:, None], pts_tgt)  # (B,H,W,3)
    z = pts_src[..., 2]
    in_front = (d > 0) & (z > MIN_DEPTH) & torch.isfinite(z)
    # Invalid points get z = 1 before the division so neither values nor gradients become inf/NaN.
    z_safe = torch.where(in_front, z, torch.ones_like(z))
    xy = pts_src[..., :2] / z_safe[..., None]
    xy = torch.where(in_front[..., None], xy, torch.zeros_like(xy))
    fx, fy = K[:, 0, 0].view(B, 1, 1), K[:, 1, 1].view(B, 1, 1)
    cx, cy = K[:, 0, 2].view(B, 1, 1), K[:, 1, 2].view(B, 1, 1)
    skew = K[:, 0, 1].view(B, 1, 1)
    u = fx * xy[..., 0] + skew * xy[..., 1] + cx
    v = fy * xy[..., 1] + cy
    return torch.stack([u, v], dim=-1), z, in_front


def sample_at(src: torch.Tensor, uv: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Bilinearly sample src (B,C,H,W) at pixel coordinates uv (B,h,w,2); zero where not valid (B,h,w)."""
    H, W = src.shape[-2:]
    grid = normalize_pixel_coordinates(uv, H, W)
    # Invalid pixels sample far outside the image (zeros padding) instead of at an arbitrary location.
    grid = torch.where(valid[..., None], grid, torch.full_like(grid, -2.0))
    # A bf16 grid is off by up to 1/256 of the image (0.5 px at 256^2): sample in float32 at least.
    dtype = torch.promote_types(src.dtype, torch.float32)
    out = F.grid_sample(src.to(dtype), grid.to(dtype), mode="bilinear", padding_mode="zeros", align_corners=True)
    return out.to(src.dtype)


def inverse_warp(src: torch.Tensor, depth_tgt: torch.Tensor, K: torch.Tensor, T_tgt_src: torch.Tensor):
    """Warp a source image (or feature map) into the target view using the target depth.

    p_s ~ K · T_src_tgt · D_t(p_t) · K^-1 · p_t, bilinear sampling at p_s.

    Args:
        src: (B,C,H,W) source image or features.
        depth_tgt: (B,1,H,W) target depth (z, pose units); <= 0 means no data.
        K: (B,3,3) intrinsics in pixels at this resolution (same camera for both views).
        T_tgt_src: (B,4,4) maps source-camera points into the target camera.
    Returns:
        warped (B,C,H,W), zero where invalid;
        valid (B,1,H,W) float mask: target pixels whose source point is in front of the source camera
        and inside the source image. Never NaN/Inf, also for points behind the camera.
    """
    _check(src.dim() == 4, f"src must be (B,C,H,W), got {tuple(src.shape)}")
    _check(depth_tgt.dim() == 4 and depth_tgt.shape[1] == 1,
           f"depth_tgt must be (B,1,H,W), got {tuple(depth_tgt.shape)}")
    _check(src.shape[0] == depth_tgt.shape[0] and src.shape[-2:] == depth_tgt.shape[-2:],
           f"src {tuple(src.shape)} and depth_tgt {tuple(depth_tgt.shape)} disagree in batch or size")
    H, W = src.shape[-2:]
    uv, _, in_front = project_to_source(depth_tgt, K, T_tgt_src)
    tol = BORDER_TOLERANCE
    u, v = uv[..., 0], uv[..., 1]
    inside = (u >= -tol) & (u <= W - 1 + tol) & (v >= -tol) & (v <= H - 1 + tol)
    valid = in_front & inside
    warped = sample_at(src, uv, valid)
    return warped, valid[:, None].to(src.dtype)


def pose_matrix(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """[R|t] as homogeneous (B,4,4) from R (B,3,3) and t (B,3)."""
    T = torch.zeros(*R.shape[:-2], 4, 4, dtype=R.dtype, device=R.device)
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1
    return T


def about_pivot(T: torch.Tensor, pivot: torch.Tensor) -> torch.Tensor:
    """The same rigid motion expressed in coordinates centred on ``pivot``: P^-1 · T · P with P = translate(pivot).

    T (B,4,4), pivot (B,3) -> (B,4,4). For an object-centric pose [R | c - R c] about c this is [R | 0].
    """
    R, t = T[..., :3, :3], T[..., :3, 3]
    t_new = (R @ pivot[..., None])[..., 0] + t - pivot
    return pose_matrix(R, t_new)


def max_warp_displacement(K: torch.Tensor, T_tgt_src: torch.Tensor, depth_min: torch.Tensor,
                          depth_max: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Upper bound on how far ``inverse_warp`` moves any pixel: max |p_s - p_t| over the image and the depth range.

    K (B,3,3) at this resolution, T_tgt_src (B,4,4), depth_min / depth_max (B,) target depths (pose units),
    size (H, W) -> bound (B,) in pixels, float64; ``inf`` where no finite bound exists (a point of the range can
    reach z <= MIN_DEPTH in the source camera, or the depth range is not finite and positive). Exactly 0 for the
    identity pose.

    Derivation. In coordinates centred on the image (K_c = K with c shifted by -((W-1)/2, (H-1)/2), so target pixels
    p = (u, v, 1) have |u| <= U = (W-1)/2, |v| <= V = (H-1)/2) and with inverse depth w = 1/D and
    T_src_tgt = [R | t], the source pixel is p_s = q_xy / q_z with q = H p + w b, H = K_c R K_c^-1 = I + M,
    b = K_c t. Then p_s - p = N / s with
        s = q_z = 1 + m31 u + m32 v + m33 + w b_z                       (affine in u, v, w)
        N = [M_xy p - (m3 . p) p_xy] + w [b_xy - b_z p_xy]              (rotation + parallax)
    For a fixed pixel p_s moves along a line as w varies, so |p_s - p| peaks at w = 1/depth_max or 1/depth_min
    (given s > 0 in between, which holds when s > 0 at the box corners since s is affine). For each of those two w,
    |N| is bounded term by term over the box (|u'^2| <= U^2, |u v| <= U V):
        |N_x| <= |m13| + |m11 - m33| U + |m12| V + |m31| U^2 + |m32| U V + w (|b_x| + |b_z| U)
        |N_y| <= |m23| + |m21| U + |m22 - m33| V + |m31| U V + |m32| V^2 + w (|b_y| + |b_z| V)
    and s from below by its minimum over the corners, 1 + m33 - |m31| U - |m32| V + w b_z. The bound is
    max over the two w of sqrt(N_x^2 + N_y^2) / s_min. It is exact for a pure translation parallel to the image
    plane (f |t_x| / depth_min) and to first order for small rotations.
    """
    B = K.shape[0]
    _check(K.shape == (B, 3, 3), f"K must have shape (B,3,3), got {tuple(K.shape)}")
    _check(T_tgt_src.shape == (B, 4, 4), f"T_tgt_src must have shape ({B},4,4), got {tuple(T_tgt_src.shape)}")
    _check(depth_min.shape == (B,) and depth_max.shape == (B,),
           f"depth_min/depth_max must have shape ({B},), got {tuple(depth_min.shape)}, {tuple(depth_max.shape)}")
    H, W = size
    f64 = torch.float64
    with torch.autocast(device_type=K.device.type, enabled=False):
        K, T = K.detach().to(f64), T_tgt_src.detach().to(f64)
        d_lo, d_hi = depth_min.detach().to(f64), depth_max.detach().to(f64)
        U, V = (W - 1) / 2, (H - 1) / 2
        Kc = K.clone()
        Kc[:, 0, 2] -= U
        Kc[:, 1, 2] -= V
        T_src_tgt = invert_pose(T)
        # R - I and t are exactly zero for the identity pose, so the bound is exactly 0 there.
        eye = torch.eye(3, dtype=f64, device=K.device)
        M = Kc @ (T_src_tgt[:, :3, :3] - eye) @ torch.linalg.inv(Kc)
        b = (Kc @ T_src_tgt[:, :3, 3:])[..., 0]
        m = M.abs()
        rot_x = m[:, 0, 2] + (M[:, 0, 0] - M[:, 2, 2]).abs() * U + m[:, 0, 1] * V + m[:, 2, 0] * U * U \
            + m[:, 2, 1] * U * V
        rot_y = m[:, 1, 2] + m[:, 1, 0] * U + (M[:, 1, 1] - M[:, 2, 2]).abs() * V + m[:, 2, 0] * U * V \
            + m[:, 2, 1] * V * V
        par_x = b[:, 0].abs() + b[:, 2].abs() * U
        par_y = b[:, 1].abs() + b[:, 2].abs() * V
        s0 = 1 + M[:, 2, 2] - m[:, 2, 0] * U - m[:, 2, 1] * V
        ok = torch.isfinite(d_lo) & torch.isfinite(d_hi) & (d_lo > 0) & (d_hi >= d_lo)
        bound = torch.zeros(B, dtype=f64, device=K.device)
        for d in (d_lo, d_hi):
            w = 1 / torch.where(ok, d, torch.ones_like(d))
            s_min = s0 + w * b[:, 2]
            # z in the source camera is D * s, affine in D: its minimum over the range is at an end.
            ok = ok & (s_min / w > MIN_DEPTH)
            s_safe = torch.where(ok, s_min, torch.ones_like(s_min))
            bound = torch.maximum(bound, torch.hypot(rot_x + w * par_x, rot_y + w * par_y) / s_safe)
        return torch.where(ok, bound, torch.full_like(bound, float("inf")))
