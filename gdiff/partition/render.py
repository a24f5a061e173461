"""Rendering change features: through the rasterizer (any geometry) or, with the geometry
frozen, with cached per-view blending weights (a sparse [H*W, N] matrix per camera).

Conventions: see :mod:`gdiff.partition`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..cameras import stack_for_render
from ..splat.rasterize import (ALPHA_MAX, ALPHA_MIN, SIGMA_MAX, T_MIN, _pixel_pairs, _sigma,
                               covariance_3d, opacity_footprint, project_gaussians, rasterize)
from ..splat.reflection import shade
from .head import CHANGED, UNCHANGED, ChangeHead


def render_features(g, encoding: torch.Tensor, camera, background: torch.Tensor | None = None,
                    with_rgb: bool = True) -> dict[str, torch.Tensor]:
    """Render colour and classification features of Gaussians ``g`` at one camera, in one pass.

    Args:
        g: :class:`gdiff.splat.gaussians.Gaussians` (activated, e.g. ``model.at_time(t)``).
        encoding: [N, D] classification encodings (degree 0: the same in every direction).
        camera: :class:`gdiff.cameras.Camera` (OpenCV axes, c2w, pixel centres at +0.5).
        background: [3] colour blended behind the RGB channels (None = black). The features
            get no background term: where nothing is hit ``F`` = 0.
        with_rgb: also render the colour (SH evaluated from the camera centre).
    Returns:
        dict ``features`` [H, W, D], ``alpha`` [H, W] and, with ``with_rgb``, ``rgb`` [H, W, 3]
        (sRGB-encoded values as fitted). Differentiable w.r.t. ``g`` and ``encoding``.
    """
    dev = g.means.device
    viewmats, Ks = stack_for_render([camera], device=dev, dtype=g.means.dtype)
    feats = encoding
    if with_rgb:
        campos = torch.as_tensor(camera.center, dtype=g.means.dtype, device=dev)
        rgb = shade(g, campos[None])[0]  # [N, 3]
        feats = torch.cat([rgb, encoding], dim=-1)
    render, alpha, _ = rasterize(g.means, g.quats, g.scales, g.opacities, feats, viewmats, Ks,
                                 camera.width, camera.height)
    render, alpha = render[0], alpha[0, ..., 0]
    out = {"alpha": alpha}
    if with_rgb:
        rgb = render[..., :3]
        if background is not None:
            rgb = rgb + (1.0 - alpha)[..., None] * background.to(rgb)
        out["rgb"] = rgb
        out["features"] = render[..., 3:]
    else:
        out["features"] = render
    return out


# --------------------------------------------------------------------------------------------
# cached blend weights (frozen geometry)


@dataclass
class BlendWeights:
    """The compositing weights of one camera: ``F[pix] = sum_p weight[p] * e[gid[p]]``.

    With the geometry fixed the rasterizer is linear in the features, so a key view's rendered
    features are a sparse matrix [H*W, N] times the encodings. Storing its non-zeros lets
    training skip projection, sorting and compositing at every step.

    Attributes:
        pix: [P] int32 flat pixel index ``row * width + col`` (sorted).
        gid: [P] int32 Gaussian index.
        weight: [P] float32 ``alpha_i T_i`` (the blending weight, as in the rasterizer).
        alpha: [H*W] float32 accumulated opacity ``sum of weights`` per pixel.
        width, height: image size (px).
    """

    pix: torch.Tensor
    gid: torch.Tensor
    weight: torch.Tensor
    alpha: torch.Tensor
    width: int
    height: int

    @property
    def nbytes(self) -> int:
        return sum(x.element_size() * x.numel() for x in (self.pix, self.gid, self.weight))


@torch.no_grad()
def blend_weights(g, camera) -> BlendWeights:
    """The blending weights of Gaussians ``g`` (activated, e.g. ``model.at_time(t)``) at
    ``camera`` (:class:`gdiff.cameras.Camera`, OpenCV axes, pixel centres at +0.5).

    Same maths as :func:`gdiff.splat.rasterize.rasterize` (EWA projection with its default
    near/far planes and 0.3 px^2 dilation, 3-sigma ellipse, alpha = min(0.99, o exp(-sigma))
    skipped below 1/255, front-to-back in depth order, compositing stopped at T <= 1e-4), so
    ``render_blended(weights, e)`` equals the rasterized features of ``e`` (no background).
    Memory: 12 bytes per (pixel, Gaussian) pair, about 30-40 pairs per pixel on fitted scenes.
    """
    dev = g.means.device
    W, H = camera.width, camera.height
    viewmats, Ks = stack_for_render([camera], device=dev, dtype=g.means.dtype)
    proj = project_gaussians(g.means, covariance_3d(g.quats, g.scales), viewmats, Ks, W, H)
    ext, drawn = opacity_footprint(proj["extents"], proj["visible"], g.opacities)
    vis = drawn[0].nonzero(as_tuple=True)[0]
    gids = vis[torch.argsort(proj["depths"][0, vis], stable=True)]  # depth order
    m2d, con, opa = proj["means2d"][0, gids], proj["conics"][0, gids], g.opacities[gids]
    src, px, py = _pixel_pairs(m2d, ext[0, gids], W, H)
    sig = _sigma(m2d[src], con[src], px, py)
    raw = opa[src] * torch.exp(-sig)
    keep = (sig <= SIGMA_MAX) & (sig >= 0) & (torch.clamp_max(raw, ALPHA_MAX) >= ALPHA_MIN)
    src, pix = src[keep], (py * W + px)[keep]
    alpha = torch.clamp_max(raw[keep], ALPHA_MAX)
    del sig, raw, px, py
    order = torch.argsort(pix * max(len(gids), 1) + src)  # by pixel, then depth
    src, pix, alpha = src[order], pix[order], alpha[order]
    logt = torch.log1p(-alpha.double())
    excl = torch.cumsum(logt, 0) - logt  # log transmittance before each pair (running)
    _, counts = torch.unique_consecutive(pix, return_counts=True)
    start = torch.cumsum(counts, 0) - counts
    T = torch.exp(excl - torch.repeat_interleave(excl[start], counts, output_size=len(pix)))
    live = (T * (1.0 - alpha.double())) > T_MIN
    w = (alpha * T.to(alpha.dtype))[live].float()
    pix = pix[live]
    acc = torch.zeros(H * W, dtype=torch.float32, device=dev).index_add_(0, pix, w)
    return BlendWeights(pix.int(), gids[src[live]].int(), w, acc, W, H)


def render_blended(bw: BlendWeights, values: torch.Tensor) -> torch.Tensor:
    """Blend per-Gaussian ``values`` [N] or [N, D] with cached weights: [H, W] or [H, W, D]
    (no background term). Differentiable w.r.t. ``values``."""
    v = values.index_select(0, bw.gid)  # its backward (index_add) sums in a fixed order
    w = bw.weight.to(values.dtype)
    v = v * (w if v.dim() == 1 else w[:, None])
    out = values.new_zeros((bw.height * bw.width,) + tuple(values.shape[1:])).index_add(
        0, bw.pix, v)
    return out.reshape((bw.height, bw.width) + tuple(values.shape[1:]))


def change_logit_parts(head: ChangeHead) -> tuple[torch.Tensor, torch.Tensor]:
    """``(d . e_i for every Gaussian [N], b_d scalar)``: the head is affine, so the rendered
    change logit ``z = Conv(F)[changed] - Conv(F)[unchanged]`` of features ``F = sum_i w_i e_i``
    is ``sum_i w_i (d . e_i) + b_d`` (``d``, ``b_d`` the differences of the conv's weight rows
    and biases): blending one number per Gaussian gives the same map as blending D."""
    w = head.conv.weight[:, :, 0, 0]
    d = w[CHANGED] - w[UNCHANGED]
    return head.encoding @ d, head.conv.bias[CHANGED] - head.conv.bias[UNCHANGED]


def blended_change_logit(head: ChangeHead, bw: BlendWeights) -> torch.Tensor:
    """The rendered change logit [H, W] from cached weights (see :func:`change_logit_parts`)."""
    zg, b = change_logit_parts(head)
    return render_blended(bw, zg) + b
