"""Rendering change features: through the rasterizer (any geometry) or, with the geometry
frozen, with cached per-view blending weights (a sparse [H*W, N] matrix per camera).

Conventions: see :mod:`gdiff.partition`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..cameras import stack_for_render
from ..splat.rasterize import (ALPHA_MAX, ALPHA_MIN, SIGMA_MAX, T_MIN, _pick_backend, _sigma,
                               covariance_3d, opacity_footprint, project_gaussians, rasterize)
from ..splat import csrc
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

# candidate (pixel, Gaussian) pairs handled at once while computing blend weights: bounds the
# transient memory (about 50 bytes a candidate) independently of the image size
BLEND_BAND_PAIRS = 1 << 22


@dataclass
class BlendWeights:
    """The compositing weights of one camera: ``F[pix] = sum_p weight[p] * e[gid[p]]``.

    With the geometry fixed the rasterizer is linear in the features, so a key view's rendered
    features are a sparse matrix [H*W, N] times the encodings. Storing its non-zeros lets
    training skip projection, sorting and compositing at every step. The matrix is stored
    row-compressed (CSR without the offsets): the pairs are grouped by pixel in row-major
    pixel order and ``counts`` says how many belong to each pixel, so a pair costs its
    Gaussian index and its weight only (6 bytes with float16 weights).

    Attributes:
        counts: [H*W] int32 number of pairs of every pixel (``row * width + col`` order).
        gid: [P] int32 Gaussian index, pixel by pixel (front to back within a pixel).
        weight: [P] blending weight ``alpha_i T_i`` (float16 or float32).
        alpha: [H*W] float32 accumulated opacity (sum of all the pixel's weights, dropped ones
            included; see :func:`blend_weights`).
        width, height: image size (px).
    """

    counts: torch.Tensor
    gid: torch.Tensor
    weight: torch.Tensor
    alpha: torch.Tensor
    width: int
    height: int

    @classmethod
    def from_pairs(cls, pix, gid, weight, alpha, width: int, height: int,
                   dtype: torch.dtype = torch.float32) -> "BlendWeights":
        """From (pixel, Gaussian, weight) triples in any order: ``pix`` [P] flat pixel index
        ``row * width + col``, ``gid`` [P], ``weight`` [P], ``alpha`` [H*W]."""
        pix = torch.as_tensor(pix).long()
        order = torch.argsort(pix, stable=True)
        counts = torch.bincount(pix, minlength=width * height)
        if len(counts) != width * height:
            raise ValueError(f"pixel index out of range for a {width}x{height} image")
        return cls(counts.int(), torch.as_tensor(gid)[order].int(),
                   torch.as_tensor(weight)[order].to(dtype), torch.as_tensor(alpha).float(),
                   width, height)

    @property
    def pix(self) -> torch.Tensor:
        """[P] int32 flat pixel index of every pair (expanded from ``counts``)."""
        return torch.repeat_interleave(
            torch.arange(len(self.counts), dtype=torch.int32, device=self.counts.device),
            self.counts.long(), output_size=len(self.gid))

    @property
    def nbytes(self) -> int:
        return sum(x.element_size() * x.numel() for x in (self.counts, self.gid, self.weight))


def _row_bands(lo_y, hi_y, nw, height: int, budget: int) -> list[tuple[int, int]]:
    """Split the image rows into bands [y0, y1) of at most ``budget`` candidate pairs each
    (a single row may exceed it). ``lo_y``/``hi_y`` [V] clamped box rows, ``nw`` [V] widths."""
    diff = torch.zeros(height + 1, dtype=torch.long, device=nw.device)
    diff.index_add_(0, lo_y, nw).index_add_(0, hi_y + 1, -nw)
    per_row = torch.cumsum(diff[:height], 0).cpu().tolist()
    bands, y0, acc = [], 0, 0
    for y, n in enumerate(per_row):
        if acc and acc + n > budget:
            bands.append((y0, y))
            y0, acc = y, 0
        acc += n
    bands.append((y0, height))
    return bands


@torch.no_grad()
def blend_weights(g, camera, tolerance: float = 0.0, dtype: torch.dtype = torch.float32,
                  band_pairs: int = BLEND_BAND_PAIRS, backend: str = "auto") -> BlendWeights:
    """The blending weights of Gaussians ``g`` (activated, e.g. ``model.at_time(t)``) at
    ``camera`` (:class:`gdiff.cameras.Camera`, OpenCV axes, pixel centres at +0.5).

    Same maths as :func:`gdiff.splat.rasterize.rasterize` (EWA projection with its default
    near/far planes and 0.3 px^2 dilation, 3-sigma ellipse, alpha = min(0.99, o exp(-sigma))
    skipped below 1/255, front-to-back in depth order, compositing stopped at T <= 1e-4), so
    ``render_blended(weights, e)`` equals the rasterized features of ``e`` (no background).

    Args:
        g: the Gaussians; camera: the view.
        tolerance: per pixel, the smallest weights are dropped as long as their sum stays
            <= ``tolerance`` (0 = keep all): a blended value then differs from the exact one
            by at most ``tolerance`` x the largest magnitude among the dropped values. Most
            pairs of a pixel are faint ones behind its opaque surface, so a small tolerance
            (1e-3) drops many of them.
        dtype: dtype of the stored weights (float16 halves them; relative error 2^-11).
        band_pairs: candidate pairs processed at once (rows of the image in bands) by the torch
            implementation: bounds its transient memory, the result does not depend on it.
        backend: ``auto`` (the compiled rasterizer's ``rasterize_weights`` for CPU tensors when
            it is built, else torch), ``cpp`` or ``torch`` (any device; vectorised over
            candidate pairs). Both give the same pairs; weights agree to float rounding.
    Memory: 6 (float16) or 8 (float32) bytes per kept (pixel, Gaussian) pair plus 4 per pixel.
    """
    dev = g.means.device
    W, H = camera.width, camera.height
    if backend not in ("auto", "cpp", "torch"):
        raise ValueError(f"blend_weights backend must be auto, cpp or torch, not {backend!r}")
    use_cpp = backend != "torch" and _pick_backend(backend, dev) == "cpp"
    viewmats, Ks = stack_for_render([camera], device=dev, dtype=g.means.dtype)
    proj = project_gaussians(g.means, covariance_3d(g.quats, g.scales), viewmats, Ks, W, H)
    ext, drawn = opacity_footprint(proj["extents"], proj["visible"], g.opacities)
    if use_cpp:  # the compiled rasterizer's own traversal (same tests and order)
        counts, gid, wt, alpha = csrc.load(required=True).rasterize_weights(
            proj["means2d"].float().contiguous(), proj["conics"].float().contiguous(),
            g.opacities.float()[None].contiguous(), ext.float().contiguous(),
            drawn.contiguous(), csrc.depth_order(proj["depths"], drawn).contiguous(), W, H,
            csrc.TILE_SIZE, float(tolerance))
        return BlendWeights(counts, gid, wt.to(dtype), alpha, W, H)
    vis = drawn[0].nonzero(as_tuple=True)[0]
    gids = vis[torch.argsort(proj["depths"][0, vis], stable=True)]  # depth order
    m2d, con, opa = proj["means2d"][0, gids], proj["conics"][0, gids], g.opacities[gids]
    del proj
    # the pixel boxes of _pixel_pairs, clipped to the image
    ext = ext[0, gids]
    lo = torch.floor(m2d - ext - 0.5).long()
    hi = torch.ceil(m2d + ext - 0.5).long()
    lo_x, lo_y = lo[:, 0].clamp_min(0), lo[:, 1].clamp_min(0)
    hi_x, hi_y = hi[:, 0].clamp_max(W - 1), hi[:, 1].clamp_max(H - 1)
    nw = (hi_x - lo_x + 1).clamp_min(0)
    on = (nw > 0) & (hi_y >= lo_y)
    rows = on.nonzero(as_tuple=True)[0]  # depth ranks of the Gaussians that touch the image
    lo_x, lo_y, hi_y, nw = lo_x[rows], lo_y[rows], hi_y[rows], nw[rows]
    m2d, con, opa, gids = m2d[rows], con[rows], opa[rows], gids[rows]
    counts = torch.zeros(H * W, dtype=torch.int32, device=dev)
    alpha_acc = torch.zeros(H * W, dtype=torch.float32, device=dev)
    out_gid, out_w = [], []
    for y0, y1 in _row_bands(lo_y, hi_y, nw, H, band_pairs):
        sel = ((lo_y < y1) & (hi_y >= y0)).nonzero(as_tuple=True)[0]  # still in depth order
        ly, hy = lo_y[sel].clamp_min(y0), hi_y[sel].clamp_max(y1 - 1)
        n = nw[sel] * (hy - ly + 1)
        total = int(n.sum())
        if total == 0:
            continue
        src = torch.repeat_interleave(torch.arange(len(sel), device=dev), n, output_size=total)
        local = torch.arange(total, device=dev) - (torch.cumsum(n, 0) - n)[src]
        w_ = nw[sel][src]
        px = lo_x[sel][src] + local % w_
        py = ly[src] + torch.div(local, w_, rounding_mode="floor")
        del local, w_
        src = sel[src]
        sig = _sigma(m2d[src], con[src], px, py)
        raw = opa[src] * torch.exp(-sig)
        keep = (sig <= SIGMA_MAX) & (sig >= 0) & (torch.clamp_max(raw, ALPHA_MAX) >= ALPHA_MIN)
        src, pix = src[keep], (py * W + px)[keep]
        alpha = torch.clamp_max(raw[keep], ALPHA_MAX)
        del sig, raw, px, py, keep
        if len(pix) == 0:
            continue
        order = torch.argsort(pix * max(len(gids), 1) + src)  # by pixel, then depth
        src, pix, alpha = src[order], pix[order], alpha[order]
        del order
        logt = torch.log1p(-alpha.double())
        excl = torch.cumsum(logt, 0) - logt  # log transmittance before each pair (running)
        del logt
        _, seg = torch.unique_consecutive(pix, return_counts=True)
        start = torch.cumsum(seg, 0) - seg
        T = torch.exp(excl - torch.repeat_interleave(excl[start], seg, output_size=len(pix)))
        del excl
        live = (T * (1.0 - alpha.double())) > T_MIN
        w = (alpha * T.to(alpha.dtype))[live].float()
        del T, alpha
        src, pix = src[live], pix[live]
        alpha_acc.index_add_(0, pix, w)
        if tolerance > 0:
            keep = _drop_faint(pix, w, tolerance)
            src, pix, w = src[keep], pix[keep], w[keep]
        counts += torch.bincount(pix, minlength=H * W).int()
        out_gid.append(gids[src].int())
        out_w.append(w.to(dtype))
    gid = torch.cat(out_gid) if out_gid else torch.zeros(0, dtype=torch.int32, device=dev)
    wt = torch.cat(out_w) if out_w else torch.zeros(0, dtype=dtype, device=dev)
    return BlendWeights(counts, gid, wt, alpha_acc, W, H)


def _drop_faint(pix: torch.Tensor, w: torch.Tensor, tolerance: float) -> torch.Tensor:
    """Bool [P]: pairs kept when each pixel drops its smallest weights while their sum stays
    <= ``tolerance``. ``pix`` [P] sorted (pairs grouped by pixel), ``w`` [P] weights."""
    order = torch.argsort(w, stable=True)
    order = order[torch.argsort(pix[order], stable=True)]  # by pixel, then weight ascending
    ws = w[order].double()
    _, seg = torch.unique_consecutive(pix[order], return_counts=True)
    first = torch.cumsum(seg, 0) - seg
    csum = torch.cumsum(ws, 0)  # running sum within a pixel: csum - (csum before its first)
    base = torch.repeat_interleave(csum[first] - ws[first], seg, output_size=len(ws))
    keep = torch.empty_like(pix, dtype=torch.bool)
    keep[order] = (csum - base) > tolerance
    return keep


def render_blended(bw: BlendWeights, values: torch.Tensor) -> torch.Tensor:
    """Blend per-Gaussian ``values`` [N] or [N, D] with cached weights: [H, W] or [H, W, D]
    (no background term). Differentiable w.r.t. ``values``; the blend is computed in the
    dtype of ``values``."""
    v = values.index_select(0, bw.gid)  # its backward (index_add) sums in a fixed order
    w = bw.weight.to(values.dtype)
    v = v * (w if v.dim() == 1 else w[:, None])
    out = torch.segment_reduce(v, "sum", lengths=bw.counts, axis=0, unsafe=True)
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
