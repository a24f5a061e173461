"""Differentiable 3D Gaussian splatting rasterizer (gsplat-compatible call, CPU and CUDA).

:func:`rasterize` takes the arguments of ``gsplat.rasterization`` that gdiff uses and returns
``(render_colors [C,H,W,X], render_alphas [C,H,W,1], meta)``.

Conventions
-----------
* Cameras: ``viewmats`` [C,4,4] world-to-camera with OpenCV axes (x right, y down, z forward);
  ``Ks`` [C,3,3] pinhole intrinsics in pixels. Pixel (col i, row j) has its centre at
  (i + 0.5, j + 0.5), so a point projecting to (u, v) = (fx x/z + cx, fy y/z + cy) lands on the
  pixel centre when u = i + 0.5.
* Gaussians: ``means`` [N,3] world positions, ``quats`` [N,4] rotations (w, x, y, z), any norm,
  ``scales`` [N,3] standard deviations along the rotated axes (world units, already activated),
  ``opacities`` [N] in [0, 1] (activated).
* Depth is the camera-frame z (world units).

Maths (classic 3DGS, as in the reference CUDA kernels)
------------------------------------------------------
* EWA projection: ``cov2d = J W Sigma W^T J^T + eps2d * I`` with ``eps2d = 0.3`` px^2 (low-pass
  dilation); the Jacobian uses x/z, y/z clamped to 1.3x the field of view.
* Culled (``radii == 0``, no contribution, zero gradient): z < near_plane or z > far_plane,
  degenerate covariance, or the 3-sigma box entirely outside the image.
  ``radii`` = ceil(3 sqrt(largest eigenvalue of cov2d)).
* Footprint: a Gaussian touches the pixels whose centre lies inside its 3-sigma ellipse
  (``sigma = 0.5 d^T cov2d^-1 d <= 4.5``, d = pixel centre - mean2d). The result does not
  depend on the tile size.
* ``alpha = min(0.99, opacity * exp(-sigma))``; alpha < 1/255 is skipped; Gaussians are composited
  front to back in order of depth (ties by index); compositing of a pixel stops before the
  Gaussian that would bring the transmittance T to <= 1e-4.
* ``render = sum_i c_i alpha_i T_i + T_final * background``, ``render_alpha = 1 - T_final``.
* ``render_mode``: "RGB" (features), "D" (accumulated depth ``sum w_i z_i``), "ED" (expected depth
  D / alpha), "RGB+D", "RGB+ED" (depth as the last channel); backgrounds apply to the feature
  channels only, as in gsplat.

Backends
--------
``backend="torch"`` is plain differentiable torch (any device; the reference). ``"cpp"`` is the
compiled CPU kernel of :mod:`gdiff.splat.csrc` (tile-based, early termination, std::threads),
with the projection and the SH colours also in C++ (fused kernels, same maths as the torch
code here, which stays the reference and is used when the cameras need a gradient).
``"gsplat"`` calls ``gsplat.rasterization`` (CUDA tensors only, gsplat installed). ``"auto"``
picks gsplat for CUDA tensors when installed, else the C++ kernel for CPU tensors when it builds,
else torch.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any

import torch

from .sh import num_sh_bases, sh_colors, sh_to_color

log = logging.getLogger("gdiff.splat.rasterize")

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
SIGMA_MAX = 4.5  # 3-sigma ellipse: 0.5 * 3**2
RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")
BACKENDS = ("auto", "torch", "cpp", "gsplat")


@dataclasses.dataclass
class RasterizeOptions:
    """Rasterizer settings shared by the stages that render (config section ``rasterize``).

    Build with ``gdiff.options.from_config(RasterizeOptions, config["rasterize"], "rasterize")``
    and pass ``**opts.kwargs()`` to :func:`rasterize`.
    """

    backend: str = "auto"  # auto | torch | cpp | gsplat
    near_plane: float = 0.01  # camera-frame z below which Gaussians are culled (world units)
    far_plane: float = 1e10  # camera-frame z above which Gaussians are culled
    eps2d: float = 0.3  # 2D low-pass dilation (px^2)
    radius_clip: float = 0.0  # cull Gaussians with a radius (px) <= this

    def __post_init__(self):
        if self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {', '.join(BACKENDS)}, got {self.backend!r}")
        if not 0 < self.near_plane < self.far_plane:
            raise ValueError("need 0 < near_plane < far_plane")
        if self.eps2d < 0 or self.radius_clip < 0:
            raise ValueError("eps2d and radius_clip must be >= 0")

    def kwargs(self) -> dict[str, Any]:
        """Keyword arguments for :func:`rasterize`."""
        return dataclasses.asdict(self)


# --------------------------------------------------------------------------------------------
# projection
# --------------------------------------------------------------------------------------------

def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [..., 3, 3] from quaternions [..., 4] (w, x, y, z; normalised here)."""
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(quats.shape[:-1] + (3, 3))


def covariance_3d(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """World covariance ``R S S R^T`` [N,3,3] from quats [N,4] (wxyz) and scales [N,3]."""
    M = quat_to_rotmat(quats) * scales.unsqueeze(-2)
    return M @ M.transpose(-1, -2)


def project_gaussians(means: torch.Tensor, covars: torch.Tensor, viewmats: torch.Tensor,
                      Ks: torch.Tensor, width: int, height: int, near_plane: float = 0.01,
                      far_plane: float = 1e10, eps2d: float = 0.3,
                      radius_clip: float = 0.0) -> dict[str, torch.Tensor]:
    """EWA-project 3D Gaussians into C pinhole cameras.

    Args:
        means: [N,3] world positions. covars: [N,3,3] world covariances.
        viewmats: [C,4,4] world-to-camera (OpenCV). Ks: [C,3,3].
        width, height: image size in pixels.
        near_plane, far_plane: z range kept (camera-frame z, world units).
        eps2d: low-pass dilation added to the 2D covariance diagonal (px^2).
        radius_clip: Gaussians with radius <= this (px) are culled.
    Returns:
        dict with ``means2d`` [C,N,2] (px, differentiable), ``conics`` [C,N,3] (a, b, c of the
        inverse 2D covariance [[a, b], [b, c]], differentiable), ``depths`` [C,N] (z),
        ``radii`` [C,N] int32 (0 = culled), ``extents`` [C,N,2] (3 sqrt(cov_xx), 3 sqrt(cov_yy):
        half-size of the 3-sigma ellipse's bounding box, px, detached) and ``visible`` [C,N].
        Values of culled Gaussians are finite but meaningless; their gradients are zero.
    """
    R = viewmats[:, :3, :3]  # [C,3,3]
    t = viewmats[:, :3, 3]  # [C,3]
    p = torch.einsum("cij,nj->cni", R, means) + t[:, None, :]  # [C,N,3]
    x, y, z = p.unbind(-1)
    in_range = (z >= near_plane) & (z <= far_plane)
    zs = torch.where(in_range, z, torch.ones_like(z))  # safe depth: no inf/nan in culled branches
    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos, lim_x_neg = (width - cx) / fx + 0.3 * tan_fovx, cx / fx + 0.3 * tan_fovx
    lim_y_pos, lim_y_neg = (height - cy) / fy + 0.3 * tan_fovy, cy / fy + 0.3 * tan_fovy
    tx = zs * torch.minimum(torch.maximum(x / zs, -lim_x_neg), lim_x_pos)
    ty = zs * torch.minimum(torch.maximum(y / zs, -lim_y_neg), lim_y_pos)
    zero = torch.zeros_like(zs)
    J = torch.stack([fx / zs, zero, -fx * tx / (zs * zs),
                     zero, fy / zs, -fy * ty / (zs * zs)], dim=-1).reshape(p.shape[:2] + (2, 3))
    cov_cam = torch.einsum("cij,njk,clk->cnil", R, covars, R)  # [C,N,3,3]
    cov2d = J @ cov_cam @ J.transpose(-1, -2)
    a = cov2d[..., 0, 0] + eps2d
    b = cov2d[..., 0, 1]
    c = cov2d[..., 1, 1] + eps2d
    det = a * c - b * b
    ok = in_range & (det > 0)
    det_s = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([c / det_s, -b / det_s, a / det_s], dim=-1)
    means2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], dim=-1)
    with torch.no_grad():
        mid = 0.5 * (a + c)
        lam = mid + torch.sqrt(torch.clamp_min(mid * mid - det, 0.1))
        radius = torch.ceil(3.0 * torch.sqrt(torch.clamp_min(lam, 0.0)))
        mx, my = means2d[..., 0], means2d[..., 1]
        ok = ok & (radius > radius_clip)
        ok = ok & (mx + radius > 0) & (mx - radius < width) & (my + radius > 0) & (my - radius < height)
        radii = torch.where(ok, radius, torch.zeros_like(radius)).to(torch.int32)
        extents = 3.0 * torch.sqrt(torch.stack([a, c], dim=-1).clamp_min(0.0))
    return dict(means2d=means2d, conics=conics, depths=z, radii=radii, extents=extents,
                visible=ok)


# --------------------------------------------------------------------------------------------
# pure torch rasterization (reference backend)
# --------------------------------------------------------------------------------------------

class _GatherAbsGrad(torch.autograd.Function):
    """``src[index]`` whose backward also stores sum |grad| per source row in ``src.absgrad``
    (gsplat's absgrad for densification)."""

    @staticmethod
    def forward(ctx, src, index, holder):
        ctx.save_for_backward(index)
        ctx.shape = src.shape
        ctx.holder = holder
        return src[index]

    @staticmethod
    def backward(ctx, grad):
        (index,) = ctx.saved_tensors
        g = grad.new_zeros(ctx.shape).index_add_(0, index, grad)
        ag = grad.new_zeros(ctx.shape).index_add_(0, index, grad.abs())
        ctx.holder.append(ag)
        return g, None, None


def _pixel_pairs(m2d: torch.Tensor, ext: torch.Tensor, width: int, height: int):
    """Candidate (gaussian, pixel) pairs: all pixels in each Gaussian's 3-sigma bounding box.

    ``m2d``/``ext`` [V,2]. Returns (src [P] row into m2d, px [P], py [P]) int64 tensors.
    """
    dev = m2d.device
    lo = torch.floor(m2d - ext - 0.5).long()
    hi = torch.ceil(m2d + ext - 0.5).long()
    lo_x, lo_y = lo[:, 0].clamp_min(0), lo[:, 1].clamp_min(0)
    hi_x, hi_y = hi[:, 0].clamp_max(width - 1), hi[:, 1].clamp_max(height - 1)
    nw = (hi_x - lo_x + 1).clamp_min(0)
    nh = (hi_y - lo_y + 1).clamp_min(0)
    counts = nw * nh
    total = int(counts.sum())
    src = torch.repeat_interleave(torch.arange(len(counts), device=dev), counts,
                                  output_size=total)
    start = torch.cumsum(counts, 0) - counts
    local = torch.arange(total, device=dev) - start[src]
    w = nw[src]
    return src, lo_x[src] + local % w, lo_y[src] + torch.div(local, w, rounding_mode="floor")


def _sigma(m2d, con, px, py):
    """Gaussian exponent at pixel centres; same operation order as the C++ kernel."""
    dx = m2d[:, 0] - (px.to(m2d.dtype) + 0.5)
    dy = m2d[:, 1] - (py.to(m2d.dtype) + 0.5)
    a, b, c = con.unbind(-1)
    return 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy


def rasterize_torch(means2d: torch.Tensor, conics: torch.Tensor, colors: torch.Tensor,
                    opacities: torch.Tensor, extents: torch.Tensor, visible: torch.Tensor,
                    depths: torch.Tensor, width: int, height: int,
                    absgrad: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite projected Gaussians into images with plain torch ops (differentiable).

    Packed: enumerates (pixel, Gaussian) pairs inside each 3-sigma box, keeps the ellipse and
    alpha >= 1/255 pairs, sorts them by (pixel, depth), computes transmittance with a segmented
    cumulative sum of log(1 - alpha) (float64) and scatters with ``index_add``.

    Args:
        means2d [C,N,2], conics [C,N,3], colors [C,N,D], opacities [C,N], extents [C,N,2],
        visible [C,N] bool, depths [C,N] (sort key only).
    Returns:
        (features [C,H,W,D] without background, alphas [C,H,W,1]).
    """
    C, N, D = colors.shape
    H, W = height, width
    outs, alphas = [], []
    holders = []
    for ci in range(C):
        vis = visible[ci].nonzero(as_tuple=True)[0]
        order = torch.argsort(depths[ci, vis].detach(), stable=True)
        gids = vis[order]  # visible Gaussians in depth order; row r has depth rank r
        with torch.no_grad():
            m_d, c_d = means2d[ci, gids], conics[ci, gids]
            src, px, py = _pixel_pairs(m_d, extents[ci, gids], W, H)
            sig = _sigma(m_d[src], c_d[src], px, py)
            raw = opacities[ci, gids][src] * torch.exp(-sig)
            keep = (sig <= SIGMA_MAX) & (sig >= 0) & (torch.clamp_max(raw, ALPHA_MAX) >= ALPHA_MIN)
            src, px, py = src[keep], px[keep], py[keep]
            pix = py * W + px
            key = pix * max(len(gids), 1) + src
            key, perm = torch.sort(key)
            src, pix, px, py = src[perm], pix[perm], px[perm], py[perm]
        g = gids[src]
        if absgrad and means2d.requires_grad:
            holder: list = []
            holders.append((ci, g, holder))
            m = _GatherAbsGrad.apply(means2d[ci], g, holder)
        else:
            m = means2d[ci].index_select(0, g)
        # index_select, not x[ci, g]: its backward sums a Gaussian's pixels in a fixed order
        # (a CPU index_put accumulate does not), so gradients are reproducible on threads
        sig = _sigma(m, conics[ci].index_select(0, g), px, py)
        alpha = torch.clamp_max(opacities[ci].index_select(0, g) * torch.exp(-sig), ALPHA_MAX)
        logt = torch.log1p(-alpha.double())
        csum = torch.cumsum(logt, 0)
        excl = csum - logt
        _, seg_counts = torch.unique_consecutive(pix, return_counts=True)
        seg_start = torch.cumsum(seg_counts, 0) - seg_counts
        base = torch.repeat_interleave(excl[seg_start], seg_counts, output_size=len(pix))
        T = torch.exp(excl - base)
        live = (T * (1.0 - alpha.double())) > T_MIN
        wgt = torch.where(live, alpha * T.to(alpha.dtype), torch.zeros_like(alpha))
        feat = colors[ci].index_select(0, g) * wgt[:, None]
        out = colors.new_zeros(H * W, D).index_add(0, pix, feat)
        acc = wgt.new_zeros(H * W).index_add(0, pix, wgt)
        outs.append(out.reshape(H, W, D))
        alphas.append(acc.reshape(H, W, 1))
    if holders:
        _attach_absgrad_torch(means2d, holders)
    return torch.stack(outs), torch.stack(alphas)


def _attach_absgrad_torch(means2d: torch.Tensor, holders: list) -> None:
    """Register a hook that fills ``means2d.absgrad`` [C,N,2] once the backward pass reaches it."""

    def hook(grad):
        ag = torch.zeros_like(grad)
        for ci, _, holder in holders:
            if holder:
                ag[ci] += holder.pop()
        means2d.absgrad = ag
        return grad

    means2d.register_hook(hook)


# --------------------------------------------------------------------------------------------
# public API
# --------------------------------------------------------------------------------------------

def _pick_backend(backend: str, device: torch.device) -> str:
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "gsplat":
        if device.type != "cuda" or not _gsplat_available():
            raise ValueError("backend='gsplat' needs CUDA tensors and the gsplat package")
        return "gsplat"
    if backend == "cpp":
        if device.type != "cpu":
            raise ValueError("backend='cpp' runs on CPU tensors only")
        from . import csrc
        csrc.load(required=True)
        return "cpp"
    if backend == "auto":
        if device.type == "cuda" and _gsplat_available():
            return "gsplat"
        if device.type == "cpu":
            try:
                from . import csrc
            except ImportError:
                return "torch"
            if csrc.load(required=False) is not None:
                return "cpp"
        return "torch"
    return "torch"


def _gsplat_available() -> bool:
    try:
        import gsplat  # noqa: F401
    except Exception:
        return False
    return True


def rasterize(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
              opacities: torch.Tensor, colors: torch.Tensor, viewmats: torch.Tensor,
              Ks: torch.Tensor, width: int, height: int, near_plane: float = 0.01,
              far_plane: float = 1e10, radius_clip: float = 0.0, eps2d: float = 0.3,
              sh_degree: int | None = None, packed: bool = True, tile_size: int = 16,
              backgrounds: torch.Tensor | None = None, render_mode: str = "RGB",
              sparse_grad: bool = False, absgrad: bool = False, rasterize_mode: str = "classic",
              camera_model: str = "pinhole", backend: str = "auto",
              ) -> tuple[torch.Tensor, torch.Tensor, dict[str, Any]]:
    """Render N 3D Gaussians into C cameras (gsplat ``rasterization``-compatible).

    Args:
        means: [N,3] world positions. quats: [N,4] (w,x,y,z), any norm. scales: [N,3] (> 0).
        opacities: [N] in [0,1].
        colors: features [N,D] or [C,N,D] when ``sh_degree`` is None (any D, e.g. 3 or 16);
            SH coefficients [N,K,3] or [C,N,K,3] when ``sh_degree`` is 0..3 (colour =
            SH(view direction from the camera centre) + 0.5, clamped at 0).
        viewmats: [C,4,4] world-to-camera (OpenCV axes). Ks: [C,3,3] pinhole intrinsics (px).
        width, height: image size (px); pixel centres at +0.5.
        near_plane, far_plane: camera-frame z range kept.
        radius_clip: cull Gaussians whose radius (px) is <= this.
        eps2d: 2D low-pass dilation (px^2), 0.3 as in 3DGS.
        backgrounds: [C,D] colours blended by (1 - alpha), or None (black).
        render_mode: "RGB" | "D" | "ED" | "RGB+D" | "RGB+ED" (depth = last channel).
        absgrad: also fill ``meta["means2d"].absgrad`` (sum over pixels of |d loss / d mean2d|)
            during backward.
        backend: "auto" | "torch" | "cpp" | "gsplat" (see module docstring).
        packed, tile_size, sparse_grad, rasterize_mode, camera_model: accepted for gsplat
            compatibility; only ``rasterize_mode="classic"``, ``camera_model="pinhole"`` and
            ``sparse_grad=False`` are supported. The result never depends on ``tile_size``.
    Returns:
        render_colors [C,H,W,X] (X = D, 1 or D+1), render_alphas [C,H,W,1], meta dict with
        ``means2d`` [C,N,2] (non-leaf; call ``.retain_grad()`` to read its gradient),
        ``radii`` [C,N] int32 (0 = not visible), ``depths`` [C,N], ``conics`` [C,N,3],
        ``opacities`` [C,N], ``visible`` [C,N] bool, ``width``, ``height``, ``n_cameras``,
        ``tile_size``, ``backend`` (the one used).
    """
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be one of {RENDER_MODES}, got {render_mode!r}")
    if rasterize_mode != "classic":
        raise ValueError("only rasterize_mode='classic' is implemented")
    if camera_model != "pinhole":
        raise ValueError("only camera_model='pinhole' is implemented")
    if sparse_grad:
        raise ValueError("sparse_grad=True is not supported")
    N = means.shape[0]
    C = viewmats.shape[0]
    if means.shape != (N, 3) or quats.shape != (N, 4) or scales.shape != (N, 3) \
            or opacities.shape != (N,):
        raise ValueError(f"expected means [N,3], quats [N,4], scales [N,3], opacities [N]; got "
                         f"{tuple(means.shape)}, {tuple(quats.shape)}, {tuple(scales.shape)}, "
                         f"{tuple(opacities.shape)}")
    if viewmats.shape != (C, 4, 4) or Ks.shape != (C, 3, 3):
        raise ValueError(f"expected viewmats [C,4,4] and Ks [C,3,3]; got "
                         f"{tuple(viewmats.shape)}, {tuple(Ks.shape)}")
    used = _pick_backend(backend, means.device)
    if used == "gsplat":
        return _rasterize_gsplat(**{k: v for k, v in locals().items()
                                    if k not in ("used", "N", "C", "backend")})

    if used == "cpp" and not (viewmats.requires_grad or Ks.requires_grad):
        from . import csrc
        proj = csrc.project_cpp(means, quats, scales, viewmats, Ks, width, height, near_plane,
                                far_plane, eps2d, radius_clip)
    else:
        proj = project_gaussians(means, covariance_3d(quats, scales), viewmats, Ks, width,
                                 height, near_plane, far_plane, eps2d, radius_clip)
    feats = _features(colors, sh_degree, means, viewmats, C, N, fused=used == "cpp")  # [C,N,D]
    D = feats.shape[-1]
    depth_feat = proj["depths"][..., None]
    if render_mode in ("D", "ED"):
        feats = depth_feat
    elif render_mode in ("RGB+D", "RGB+ED"):
        feats = torch.cat([feats, depth_feat], dim=-1)
    feats = feats.contiguous()
    opac = opacities[None, :].expand(C, N)
    extents, drawn = opacity_footprint(proj["extents"], proj["visible"], opacities)

    if used == "cpp":
        from . import csrc
        render, alpha = csrc.rasterize_cpp(proj["means2d"], proj["conics"], feats, opac,
                                           extents, drawn, proj["depths"],
                                           width, height, absgrad=absgrad)
    else:
        render, alpha = rasterize_torch(proj["means2d"], proj["conics"], feats, opac,
                                        extents, drawn, proj["depths"],
                                        width, height, absgrad=absgrad)
    if backgrounds is not None and render_mode not in ("D", "ED"):
        if backgrounds.shape != (C, D):
            raise ValueError(f"backgrounds must be [C,D] = [{C},{D}], got {tuple(backgrounds.shape)}")
        bg = backgrounds
        if render_mode in ("RGB+D", "RGB+ED"):
            bg = torch.cat([bg, bg.new_zeros(C, 1)], dim=-1)
        render = render + (1.0 - alpha) * bg[:, None, None, :]
    if render_mode in ("ED", "RGB+ED"):
        render = torch.cat([render[..., :-1], render[..., -1:] / alpha.clamp_min(1e-10)], dim=-1)
    meta = dict(means2d=proj["means2d"], radii=proj["radii"], depths=proj["depths"],
                conics=proj["conics"], opacities=opac, visible=proj["visible"], width=width,
                height=height, n_cameras=C, tile_size=tile_size, backend=used)
    return render, alpha, meta


@torch.no_grad()
def opacity_footprint(extents: torch.Tensor, visible: torch.Tensor, opacities: torch.Tensor
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """Shrink each Gaussian's pixel box to where it can reach ``alpha >= 1/255``.

    A pixel gets ``alpha = min(0.99, o exp(-sigma))``, skipped below 1/255, so a Gaussian of
    opacity ``o`` only touches pixels with ``sigma <= ln(255 o)``; when that is below the
    3-sigma limit (4.5) the box scales by ``sqrt(ln(255 o) / 4.5)``. The image is unchanged
    (the same pixels pass both tests); only fewer pixels are visited.

    Args: extents [C,N,2] px half-sizes of the 3-sigma boxes, visible [C,N] bool,
        opacities [N] in [0, 1].
    Returns: (extents [C,N,2], visible [C,N]) with Gaussians below 1/255 opacity dropped.
    """
    # 1e-3 of slack keeps every pixel the kernel's own float test accepts
    reach = torch.log(opacities.clamp_min(1e-12) * (1.0 / ALPHA_MIN)) + 1e-3
    scale = torch.sqrt((reach / SIGMA_MAX).clamp(0.0, 1.0))
    return extents * scale[None, :, None], visible & (reach > 0)[None, :]


def camera_centers(viewmats: torch.Tensor) -> torch.Tensor:
    """World positions [C,3] of the centres of cameras with world-to-camera ``viewmats``
    [C,4,4] (``-R^T t``)."""
    return -torch.einsum("cji,cj->ci", viewmats[:, :3, :3], viewmats[:, :3, 3])


def _features(colors, sh_degree, means, viewmats, C, N, fused=False) -> torch.Tensor:
    """Per-camera features [C,N,D]: plain features, or SH evaluated from each camera centre
    (``fused``: with the C++ kernel where it applies)."""
    if sh_degree is None:
        if colors.dim() == 2 and colors.shape[0] == N:
            return colors[None].expand(C, N, colors.shape[1])
        if colors.dim() == 3 and colors.shape[:2] == (C, N):
            return colors
        raise ValueError(f"colors must be [N,D] or [C,N,D] with N={N}, C={C} when sh_degree is "
                         f"None; got {tuple(colors.shape)}")
    K = num_sh_bases(sh_degree)
    if not (colors.dim() in (3, 4) and colors.shape[-1] == 3 and colors.shape[-2] >= K
            and colors.shape[-3] == N and (colors.dim() == 3 or colors.shape[0] == C)):
        raise ValueError(f"SH colors must be [N,K,3] or [C,N,K,3] with K >= {K} for sh_degree "
                         f"{sh_degree}; got {tuple(colors.shape)}")
    dirs = means[None, :, :] - camera_centers(viewmats)[:, None, :]  # [C,N,3]
    if colors.dim() == 3:
        return sh_colors(sh_degree, colors, dirs, fused=fused)
    return sh_to_color(sh_degree, colors, dirs)


def _rasterize_gsplat(**kw):
    """Delegate to ``gsplat.rasterization`` (CUDA); meta gets ``backend="gsplat"``."""
    import gsplat

    kw.pop("packed", None)
    render, alpha, meta = gsplat.rasterization(packed=False, **kw)
    radii = meta["radii"]
    meta["visible"] = (radii > 0).all(-1) if radii.dim() == 3 else radii > 0
    meta["backend"] = "gsplat"
    return render, alpha, meta
