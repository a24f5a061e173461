"""Gaussian partition: learn which Gaussians belong to changed instances (paper Sec. "4D Gaussian
partition"), so a change map can be rendered from any camera and time.

Model
-----
Every Gaussian ``i`` carries a learnable classification encoding ``e_i`` (``encoding_dim`` = 16
numbers, degree 0: no view dependence). The encodings are alpha-blended by the same rasterizer
as the colour, *without* a background term, into a feature map ``F`` [H, W, 16]; a 1x1
convolution ``Conv`` (16 -> 2 channels: unchanged, changed) gives the change logits.
Two classes with a softmax (rather than one logit) so that the 3D regulariser is the KL
divergence between class distributions, as in the paper; the change probability is
``softmax(Conv(F))[changed] = sigmoid(z)`` with ``z = logit_changed - logit_unchanged``, and
the 2D loss (the paper's BCE) is the binary cross-entropy of ``sigmoid(z)`` against the mask.

Because ``Conv`` is affine, ``Conv(F) = sum_i w_i Conv(e_i) + (1 - A) b`` (``w_i`` blending
weights, ``A = sum_i w_i`` the pixel's alpha, ``b`` the conv bias): where the surface is opaque
the rendered logits are the blend of the per-Gaussian logits ``Conv(e_i)``. That is why the
per-Gaussian change probability ``softmax(Conv(e_i))[changed]`` is the quantity used to split
the model into changed / unchanged Gaussians.

Training
--------
Loss: ``lambda_2d`` x BCE(rendered map, compare-stage mask of the key view) + ``lambda_3d`` x
L3d (kNN KL), plus the fit stage's L1 + L_TV when the geometry is fine-tuned too.

* Other-time pixels left out (``ignore_other_time``): a key view of time t is supervised
  with the compare stage's mask at t, except where only the mask at 1 - t is set. The 4D fit
  often draws an object that appears (or disappears) with Gaussians that are visible at the
  other time as the surface it covers (time-dependent opacity, colour, motion); one
  time-independent label per Gaussian cannot be "changed" at t1 and "unchanged" at t0, and the
  t0 views outvoted the t1 views: change maps were under-confident (synth demo with exact
  masks: F1 0.76 at 0.5, 0.94 at 0.1; the Gaussians under missed pixels had 69 % of their
  supervision "unchanged"). See :func:`ignore_weight`.
* Optional class-balanced BCE (``balance_classes``, off by default: it raises recall but
  spreads "changed" over boundary Gaussians), see :func:`bce_on_change_logit`.
* Frozen geometry (``geometry_lr_scale`` = 0, default): the fitted model already minimises
  L1 + L_TV, so only encodings and conv are trained; the rasterizer is then linear in the
  features and each key view's blending weights are computed once (:func:`blend_weights`, a
  sparse [H*W, N] matrix), and a step blends one change logit per Gaussian
  (:func:`blended_change_logit`) instead of deforming the model and rasterizing colour +
  encodings forward and backward. ``geometry_lr_scale`` > 0 fine-tunes the fitted Gaussians
  jointly (the paper's total loss), rendering every step.

Conventions: cameras are :class:`gdiff.cameras.Camera` (OpenCV axes, c2w camera-to-world,
pixel centres at +0.5); time ``t`` in [0, 1] (before = 0, after = 1); probability maps are
float32 [H, W] in [0, 1]; masks bool [H, W] (written as 8-bit PNG, 255 = changed).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from .knn import NeighbourIndex

log = logging.getLogger("gdiff.partition")

UNCHANGED, CHANGED = 0, 1


@dataclass
class PartitionOptions:
    """Options of the ``partition`` stage (config section ``partition``)."""

    iterations: int = 600             # fine-tuning steps (one training image per step)
    encoding_dim: int = 16            # length of the per-Gaussian classification encoding
    lambda_2d: float = 1.0            # weight of the BCE between rendered and target masks
    ignore_other_time: bool = True    # leave pixels changed only at the other time out of the BCE
    balance_classes: bool = False     # BCE = (mean over changed + mean over unchanged pixels) / 2
    lambda_3d: float = 2.0            # weight of the kNN KL regulariser L3d
    knn_k: int = 5                    # neighbours per sampled Gaussian in L3d
    knn_samples: int = 1000           # Gaussians sampled per L3d evaluation (m)
    l3d_every: int = 2                # evaluate L3d every this many iterations
    knn_refresh: int = 200            # rebuild the KD-tree of centres every this many L3d calls
    lr_encoding: float = 0.02         # Adam learning rate of the encodings
    lr_head: float = 0.005            # Adam learning rate of the 1x1 convolution
    geometry_lr_scale: float = 0.0    # x the fit's final learning rates; 0 = frozen geometry
                                      # (blend weights cached per key view: fast), > 0 = joint
                                      # fine-tuning with L1 + L_TV (renders every step)
    lambda_tv: float | None = None    # weight of the HexPlane TV; None = the fit stage's value
    threshold: float = 0.5            # probability above which a pixel / Gaussian is "changed"
    max_side: int | None = None       # longest image side for training; None = the fit's, 0 = full
    checkpoint_every: int = 500       # write a resumable checkpoint every this many steps
    log_every: int = 50               # rows of train_log.csv
    seed: int = 0

    def __post_init__(self):
        if self.iterations < 0:
            raise ValueError("iterations must be >= 0")
        if self.encoding_dim < 1:
            raise ValueError("encoding_dim must be >= 1")
        if self.knn_k < 1 or self.knn_samples < 1:
            raise ValueError("knn_k and knn_samples must be >= 1")
        if self.l3d_every < 1 or self.knn_refresh < 1:
            raise ValueError("l3d_every and knn_refresh must be >= 1")
        if not 0.0 < self.threshold < 1.0:
            raise ValueError("threshold must lie in (0, 1)")
        if self.lambda_2d < 0 or self.lambda_3d < 0:
            raise ValueError("lambda_2d and lambda_3d must be >= 0")
        if self.max_side is not None and self.max_side < 0:
            raise ValueError("max_side must be >= 0 (0 = full resolution)")
        if self.checkpoint_every < 1 or self.log_every < 1:
            raise ValueError("checkpoint_every and log_every must be >= 1")


class ChangeHead(nn.Module):
    """Per-Gaussian classification encodings and the 1x1 convolution that classifies them.

    Attributes:
        encoding: [N, D] learnable encodings (D = ``dim``, 16 by default).
        conv: ``nn.Conv2d(D, 2, 1)``; output channel 0 = unchanged, 1 = changed.
    """

    def __init__(self, n: int, dim: int = 16, seed: int = 0):
        super().__init__()
        g = torch.Generator().manual_seed(seed)
        # Small random encodings: Gaussians start undecided but distinguishable.
        self.encoding = nn.Parameter(0.1 * torch.randn(n, dim, generator=g))
        self.conv = nn.Conv2d(dim, 2, kernel_size=1)
        with torch.no_grad():  # PyTorch's default range, drawn from the seeded generator
            bound = 1.0 / dim ** 0.5
            self.conv.weight.uniform_(-bound, bound, generator=g)
            self.conv.bias.uniform_(-bound, bound, generator=g)

    @property
    def n(self) -> int:
        return self.encoding.shape[0]

    @property
    def dim(self) -> int:
        return self.encoding.shape[1]

    def classify(self, features: torch.Tensor) -> torch.Tensor:
        """Apply the 1x1 convolution to features in channels-last layout.

        Args:
            features: [..., D] (a rendered map [C, H, W, D] or encodings [N, D]).
        Returns:
            logits [..., 2] (unchanged, changed).
        """
        w = self.conv.weight[:, :, 0, 0]
        return F.linear(features, w, self.conv.bias)

    def gaussian_logits(self) -> torch.Tensor:
        """Per-Gaussian class logits ``Conv(e_i)``, [N, 2]."""
        return self.classify(self.encoding)

    def gaussian_probability(self) -> torch.Tensor:
        """Per-Gaussian change probability ``softmax(Conv(e_i))[changed]``, [N] in [0, 1]."""
        return change_probability(self.gaussian_logits())


def change_logit(logits: torch.Tensor) -> torch.Tensor:
    """``logit_changed - logit_unchanged`` ([..., 2] -> [...]); sigmoid of it = softmax[changed]."""
    return logits[..., CHANGED] - logits[..., UNCHANGED]


def change_probability(logits: torch.Tensor) -> torch.Tensor:
    """softmax over the two classes, changed channel: [..., 2] -> [...] in [0, 1]."""
    return torch.sigmoid(change_logit(logits))


def mask_bce(logits: torch.Tensor, target: torch.Tensor, pos_fraction: float | None = None
             ) -> torch.Tensor:
    """The 2D loss: binary cross-entropy of the rendered change probability against a mask.

    Args:
        logits: [..., H, W, 2] rendered class logits.
        target: [..., H, W] mask (bool or float in [0, 1]; 1 = changed).
        pos_fraction: None = plain mean over pixels (the paper's 1/|M| normalisation); else
            the fraction f of changed pixels over all training masks, and the loss is class
            balanced (see :func:`bce_on_change_logit`).
    Returns:
        scalar.
    """
    return bce_on_change_logit(change_logit(logits), target, pos_fraction)


def bce_on_change_logit(z: torch.Tensor, target: torch.Tensor,
                        pos_fraction: float | None = None,
                        weight: torch.Tensor | None = None) -> torch.Tensor:
    """BCE of ``sigmoid(z)`` against ``target`` (same shapes; 1 = changed), mean over pixels.

    With ``pos_fraction`` = f in (0, 1) every changed pixel is weighted ``0.5 / f`` and every
    unchanged one ``0.5 / (1 - f)`` (soft targets interpolate): over the training set this is
    (mean loss on changed pixels + mean loss on unchanged pixels) / 2, so the few changed
    pixels (often < 5 %) count as much as the background and a Gaussian seen changed in some
    views and unchanged in others is not decided by pixel counts alone. The weights have mean 1
    over the training set, so the loss keeps the scale of the plain BCE (and its balance with
    L3d). f outside (0, 1) (no changed or no unchanged pixel anywhere) gives the plain BCE.
    ``weight`` (same shape, in [0, 1]; see :func:`ignore_weight`) multiplies every pixel's
    term (0 = pixel left out); the mean is still over all pixels.
    """
    target = target.to(z.dtype)
    w = None if weight is None else weight.to(z.dtype)
    if pos_fraction is not None and 0.0 < pos_fraction < 1.0:
        cw = target * (0.5 / pos_fraction) + (1.0 - target) * (0.5 / (1.0 - pos_fraction))
        w = cw if w is None else w * cw
    return F.binary_cross_entropy_with_logits(z, target, weight=w)


def ignore_weight(own, other) -> np.ndarray:
    """Per-pixel BCE weight of a key view: 0 where only the *other* time's mask is set.

    ``own`` is the view's target (changed objects present at its time t), ``other`` the
    compare stage's mask at 1 - t (both [H, W] in [0, 1]). Pixels in ``other`` but not in
    ``own`` show, at time t, the surface where an object appears or disappears at 1 - t. The
    4D fit often draws such an object with Gaussians that are visible at t as that surface
    (through time-dependent opacity, colour or motion), and a Gaussian's change label does not
    depend on time: calling those pixels unchanged would fight the other time's positive
    supervision (on synth demo the Gaussians under missed changed pixels saw 69 % unchanged
    supervision). They are left out: weight ``1 - other (1 - own)``, float32 [H, W].
    """
    own, other = np.asarray(own, np.float32), np.asarray(other, np.float32)
    return (1.0 - other * (1.0 - own)).astype(np.float32)


def changed_fraction(targets, weights=None) -> float:
    """Fraction of changed pixels (sum of soft target values / pixel count) over ``targets``
    (an iterable of [H, W] tensors or arrays in [0, 1]); with ``weights`` (an iterable of the
    same shapes, or of None) a weighted fraction, so ignored pixels do not count."""
    pos = tot = 0.0
    weights = weights if weights is not None else [None] * len(targets)
    for t, w in zip(targets, weights):
        t = torch.as_tensor(t).double()
        w = torch.ones_like(t) if w is None else torch.as_tensor(w).double()
        pos += float((t * w).sum())
        tot += float(w.sum())
    return pos / tot if tot else 0.0


def neighbour_kl(logits: torch.Tensor, sample: torch.Tensor, neighbours: torch.Tensor
                 ) -> torch.Tensor:
    """The 3D regulariser L3d: mean KL(P_j || P_i) over sampled Gaussians j and their neighbours i.

    ``P = softmax(Conv(e))`` over the two classes.

    Args:
        logits: [N, 2] per-Gaussian logits (``ChangeHead.gaussian_logits()``).
        sample: [m] indices of the sampled Gaussians.
        neighbours: [m, k] indices of each sample's k nearest Gaussians in 3D.
    Returns:
        scalar = 1/(m k) sum_j sum_i KL(P_j || P_i), in nats.
    """
    logp = F.log_softmax(logits, dim=-1)
    ls = logp[sample].unsqueeze(1)           # [m, 1, 2]
    ln = logp[neighbours]                    # [m, k, 2]
    return (ls.exp() * (ls - ln)).sum(-1).mean()


def neighbour_disagreement(prob: torch.Tensor | np.ndarray, neighbours: np.ndarray,
                           sample: np.ndarray) -> float:
    """Mean |p_j - p_i| between sampled Gaussians j and their k neighbours i (a diagnostic).

    Args:
        prob: [N] per-Gaussian change probability.
        sample: [m] indices; neighbours: [m, k] indices.
    """
    p = prob.detach().cpu().numpy() if isinstance(prob, torch.Tensor) else np.asarray(prob)
    return float(np.abs(p[np.asarray(sample)][:, None] - p[np.asarray(neighbours)]).mean())


def l3d_step(head: ChangeHead, means: torch.Tensor, index: NeighbourIndex) -> torch.Tensor:
    """One evaluation of L3d: sample Gaussians, look up their neighbours among ``means`` [N, 3]
    (world units, detached for the look-up), return :func:`neighbour_kl`."""
    sample, nbr = index.sample(means)
    return neighbour_kl(head.gaussian_logits(), sample, nbr)


# --------------------------------------------------------------------------------------------
# rendering


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
    from .cameras import stack_for_render
    from .splat.rasterize import rasterize
    from .splat.sh import sh_to_color

    dev = g.means.device
    viewmats, Ks = stack_for_render([camera], device=dev, dtype=g.means.dtype)
    feats = encoding
    if with_rgb:
        campos = torch.as_tensor(camera.center, dtype=g.means.dtype, device=dev)
        rgb = sh_to_color(g.sh_degree, g.sh, g.means - campos)  # [N, 3]
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
    from .cameras import stack_for_render
    from .splat.rasterize import (ALPHA_MAX, ALPHA_MIN, SIGMA_MAX, T_MIN, _pixel_pairs, _sigma,
                                  covariance_3d, opacity_footprint, project_gaussians)

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
    v = values[bw.gid]
    w = bw.weight.to(values.dtype)
    v = v * (w if v.dim() == 1 else w[:, None])
    out = values.new_zeros((bw.height * bw.width,) + tuple(values.shape[1:])).index_add(
        0, bw.pix, v)
    return out.reshape((bw.height, bw.width) + tuple(values.shape[1:]))


def blended_change_logit(head: "ChangeHead", bw: BlendWeights) -> torch.Tensor:
    """The rendered change logit ``z = Conv(F)[changed] - Conv(F)[unchanged]`` [H, W] from cached
    weights: the head is affine, so ``z = sum_i w_i (d . e_i) + b_d`` with ``d``, ``b_d`` the
    differences of the conv's weight rows and biases (1 channel blended instead of D)."""
    w = head.conv.weight[:, :, 0, 0]
    d = w[CHANGED] - w[UNCHANGED]
    b = head.conv.bias[CHANGED] - head.conv.bias[UNCHANGED]
    return render_blended(bw, head.encoding @ d) + b


# --------------------------------------------------------------------------------------------
# the partition model: fitted 4D Gaussians + change head


FORMAT = "gdiff.PartitionModel"
VERSION = 1


class PartitionModel(nn.Module):
    """A fine-tuned 4D Gaussian model with per-Gaussian change encodings.

    Attributes:
        fit: :class:`gdiff.splat.model.GaussianModel4D`.
        head: :class:`ChangeHead` with one encoding per Gaussian of ``fit``.
        camera: default :class:`gdiff.cameras.Camera` (the training intrinsics; pose identity),
            used by the CLI when no intrinsics are given.
        background: [3] colour behind the rendered images (the fit stage's).
        threshold: probability above which a pixel / Gaussian counts as changed.
    """

    def __init__(self, fit, head: ChangeHead, camera, background=None, threshold: float = 0.5):
        super().__init__()
        if head.n != len(fit):
            raise ValueError(f"head has {head.n} encodings but the model {len(fit)} Gaussians")
        self.fit = fit
        self.head = head
        self.camera = camera
        bg = torch.zeros(3) if background is None else torch.as_tensor(background).float()
        self.register_buffer("background", bg.reshape(3).clone())
        self.threshold = float(threshold)

    def render(self, camera, t: float, with_rgb: bool = False) -> dict[str, torch.Tensor]:
        """Render at ``camera`` and time ``t``: dict ``logits`` [H, W, 2], ``prob`` [H, W]
        (change probability), ``alpha`` [H, W] and, with ``with_rgb``, ``rgb`` [H, W, 3]."""
        g = self.fit.at_time(float(t))
        out = render_features(g, self.head.encoding, camera, self.background, with_rgb)
        out["logits"] = self.head.classify(out.pop("features"))
        out["prob"] = change_probability(out["logits"])
        return out

    def gaussian_probability(self) -> torch.Tensor:
        """Per-Gaussian change probability [N] in [0, 1]."""
        return self.head.gaussian_probability()


@torch.no_grad()
def render_change_map(pmodel: PartitionModel, camera, t: float | None = None,
                      with_image: bool = False) -> dict[str, np.ndarray | None]:
    """The change map of a viewpoint.

    Args:
        pmodel: from :func:`load_partition_model` or :func:`train_partition`.
        camera: :class:`gdiff.cameras.Camera` (any pose and intrinsics).
        t: time in [0, 1], or None for the union of t = 0 (what was there and changed) and
            t = 1 (what is there and is new).
        with_image: also return the rendered colour image(s).
    Returns:
        dict of numpy arrays: ``prob`` [H, W] float32 in [0, 1] (for t=None the per-pixel max of
        the two times), ``mask`` [H, W] bool (``prob > pmodel.threshold``), ``prob_t0`` and
        ``prob_t1`` (None when that time was not rendered) and, with ``with_image``,
        ``image`` [H, W, 3] float32 sRGB (the render at ``t``; for t=None at t=0) plus
        ``image_t0`` / ``image_t1``.
    """
    times = [0.0, 1.0] if t is None else [float(t)]
    if not all(0.0 <= x <= 1.0 for x in times):
        raise ValueError(f"t must lie in [0, 1], got {t}")
    res = {}
    for x in times:
        r = pmodel.render(camera, x, with_rgb=with_image)
        res[x] = {k: v.detach().float().cpu().numpy() for k, v in r.items()}
    out: dict[str, np.ndarray | None] = {
        "prob_t0": res[0.0]["prob"] if 0.0 in res else None,
        "prob_t1": res[1.0]["prob"] if 1.0 in res else None,
    }
    if t is None:
        out["prob"] = np.maximum(out["prob_t0"], out["prob_t1"])
    else:
        out["prob"] = res[times[0]]["prob"]
    out["prob"] = out["prob"].astype(np.float32)
    out["mask"] = out["prob"] > pmodel.threshold
    if with_image:
        out["image_t0"] = np.clip(res[0.0]["rgb"], 0, 1) if 0.0 in res else None
        out["image_t1"] = np.clip(res[1.0]["rgb"], 0, 1) if 1.0 in res else None
        out["image"] = np.clip(res[times[0]]["rgb"], 0, 1)
    return out


def _camera_to_dict(cam) -> dict:
    return {k: getattr(cam, k) for k in ("width", "height", "fx", "fy", "cx", "cy")}


def partition_blob(pmodel: PartitionModel, options: PartitionOptions | None = None) -> dict:
    """Everything :func:`load_partition_model` needs, as a torch-saveable dict."""
    import dataclasses

    fit = pmodel.fit
    return {"format": FORMAT, "version": VERSION,
            "fit": {"config": fit.config(),
                    "state_dict": {k: v.detach().cpu() for k, v in fit.state_dict().items()},
                    "meta": getattr(fit, "meta", {})},
            "head": {k: v.detach().cpu() for k, v in pmodel.head.state_dict().items()},
            "camera": _camera_to_dict(pmodel.camera),
            "background": pmodel.background.detach().cpu().tolist(),
            "threshold": pmodel.threshold,
            "options": dataclasses.asdict(options) if options is not None else {}}


def save_partition_model(pmodel: PartitionModel, path, options: PartitionOptions | None = None
                         ) -> None:
    """Write the partition ``model.pt`` atomically (format ``gdiff.PartitionModel``)."""
    from .io import atomic_path

    with atomic_path(path) as tmp:
        torch.save(partition_blob(pmodel, options), tmp)


def load_partition_model(path, device="auto") -> PartitionModel:
    """Load a partition ``model.pt`` onto ``device`` (``auto``/``cpu``/``cuda`` or a
    ``torch.device``), in eval mode. Raises :class:`gdiff.errors.ModelFileError` naming the
    file when it is missing or not a partition model."""
    from pathlib import Path

    from .cameras import Camera
    from .device import resolve_device
    from .errors import ModelFileError
    from .splat.model import GaussianModel4D

    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"{path}: partition model not found; run the partition stage "
                             "(snakemake ... partition) first")
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise ModelFileError(f"{path}: cannot be read ({e}); delete it and rerun the partition "
                             "stage") from None
    if not isinstance(blob, dict) or blob.get("format") != FORMAT:
        hint = (" (this is a fit-stage model; pass results/<scene>/partition/model.pt)"
                if isinstance(blob, dict) and blob.get("format") == "gdiff.GaussianModel4D"
                else "")
        raise ModelFileError(f"{path}: not a gdiff partition model{hint}")
    if blob.get("version", 0) > VERSION:
        raise ModelFileError(f"{path}: written by a newer gdiff (version {blob['version']}); "
                             "update gdiff")
    return _from_blob(blob, resolve_device(device), Camera, GaussianModel4D)


def _from_blob(blob, device, Camera, GaussianModel4D) -> PartitionModel:
    fit = GaussianModel4D.from_state(blob["fit"]["config"], blob["fit"]["state_dict"])
    fit.meta = blob["fit"].get("meta", {})
    enc = blob["head"]["encoding"]
    head = ChangeHead(enc.shape[0], enc.shape[1])
    head.load_state_dict(blob["head"])
    cam = Camera(**blob["camera"])
    pm = PartitionModel(fit, head, cam, blob.get("background"), blob.get("threshold", 0.5))
    return pm.to(device).eval()


# --------------------------------------------------------------------------------------------
# training data: key poses with their images and target masks


@dataclass
class KeyView:
    """One key pose used for training: a source photo and the compare stage's masks there.

    ``camera`` is at training resolution; ``time`` the photo's time (0 before, 1 after);
    ``image`` the photo; ``masks`` maps "t0", "t1", "union" to mask files (absolute paths);
    the training target of the photo is ``masks[f"t{time}"]``.
    """

    name: str
    camera: object
    time: float
    image: object
    masks: dict

    @property
    def target(self):
        return self.masks[f"t{int(round(self.time))}"]

    @property
    def other(self):
        """The mask of the other time (what changed but is drawn at 1 - time)."""
        return self.masks[f"t{1 - int(round(self.time))}"]


KEYFRAME_COLUMNS = ("path", "frame", "image", "set", "time", "mask_t0", "mask_t1", "mask_union")


def read_key_views(keyframes_csv, cameras_json, scene_dir, max_side: int = 0) -> list[KeyView]:
    """Join ``change/keyframes.csv`` with ``poses/cameras.json``.

    Mask paths in the CSV are relative to ``results/<scene>/`` (the CSV's grandparent folder);
    image paths are relative to ``scene_dir``. Cameras are scaled so that max(width, height)
    <= ``max_side`` (0 = full size). Raises :class:`gdiff.errors.SceneError` naming the file and
    row for missing columns, unknown images or missing files.
    """
    from pathlib import Path

    import pandas as pd

    from .cameras import load_cameras
    from .errors import SceneError

    keyframes_csv, scene_dir = Path(keyframes_csv), Path(scene_dir)
    try:
        df = pd.read_csv(keyframes_csv)
    except FileNotFoundError:
        raise SceneError(f"{keyframes_csv}: not found; run the compare stage first") from None
    missing = [c for c in KEYFRAME_COLUMNS if c not in df.columns]
    if missing:
        raise SceneError(f"{keyframes_csv}: missing column(s) {', '.join(missing)}; rerun the "
                         "compare stage")
    if df.empty:
        raise SceneError(f"{keyframes_csv}: no key poses; the compare stage found no key frames")
    cams = {Path(c.image).as_posix(): c for c in load_cameras(cameras_json) if c.image}
    root = keyframes_csv.parent.parent
    views = []
    for i, row in df.iterrows():
        img = Path(str(row["image"])).as_posix()
        cam = cams.get(img)
        if cam is None:
            raise SceneError(f"{keyframes_csv}: row {i}: image {img!r} has no camera in "
                             f"{cameras_json}; rerun the poses stage (or the compare stage)")
        t = float(row["time"])
        if t not in (0.0, 1.0):
            raise SceneError(f"{keyframes_csv}: row {i}: time must be 0 or 1, got {row['time']}")
        masks = {k: root / str(row[f"mask_{k}"]) for k in ("t0", "t1", "union")}
        for k, p in masks.items():
            if not p.is_file():
                raise SceneError(f"{keyframes_csv}: row {i}: mask_{k} file {p} not found; "
                                 "rerun the compare stage")
        if max_side and max(cam.width, cam.height) > max_side:
            cam = cam.scaled(max_side / max(cam.width, cam.height))
        views.append(KeyView(f"{row['path']}_{int(row['frame']):05d}", cam, t,
                             scene_dir / img, masks))
    return views


def _load_image(path, camera) -> np.ndarray:
    """Photo as float32 [H, W, 3] sRGB in [0, 1], resized (area) to the camera's size."""
    import cv2

    from .io import read_image

    img = read_image(path)
    if img.shape[:2] != (camera.height, camera.width):
        img = cv2.resize(img, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
    return img


def _load_mask(path, camera) -> np.ndarray:
    """Mask as float32 [H, W] in [0, 1] at the camera's size (area resampling: soft edges)."""
    import cv2

    from .io import read_mask

    m = read_mask(path).astype(np.float32)
    if m.shape != (camera.height, camera.width):
        m = cv2.resize(m, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
    return m


# --------------------------------------------------------------------------------------------
# training

def _fit_options(fit) -> dict:
    """The fit stage's options as saved in ``model.meta`` (defaults of FitOptions if absent)."""
    import dataclasses

    from .splat.train import FitOptions

    saved = (getattr(fit, "meta", None) or {}).get("options") or {}
    base = dataclasses.asdict(FitOptions())
    return {**base, **{k: v for k, v in saved.items() if k in base}}


def _param_groups(pm: PartitionModel, opts: PartitionOptions, extent: float) -> list[dict]:
    """Adam groups: encodings, conv, and (unless ``geometry_lr_scale`` is 0) the fitted
    parameters at the fit stage's final learning rates x ``geometry_lr_scale``."""
    groups = [{"name": "encoding", "params": [pm.head.encoding], "lr": opts.lr_encoding},
              {"name": "conv", "params": list(pm.head.conv.parameters()), "lr": opts.lr_head}]
    s = opts.geometry_lr_scale
    fit = pm.fit
    if s <= 0:
        fit.requires_grad_(False)
        return groups
    fo = _fit_options(fit)
    lrs = {"means": fo["lr_means_final"] * extent, "scales": fo["lr_scales"],
           "quats": fo["lr_quats"], "opacities": fo["lr_opacities"], "sh0": fo["lr_sh0"],
           "shN": fo["lr_shN"]}
    for name, p in fit.splats.items():
        if name in lrs:
            groups.append({"name": name, "params": [p], "lr": lrs[name] * s})
        else:
            p.requires_grad_(False)
    if fit.deformation is not None:
        groups.append({"name": "grid", "params": fit.deformation.grid_parameters(),
                       "lr": fo["lr_grid_final"] * s})
        groups.append({"name": "deform", "params": fit.deformation.mlp_parameters(),
                       "lr": fo["lr_deform_final"] * extent * s})
    return groups


def _tv_loss(pm: PartitionModel, lambda_tv: float | None) -> torch.Tensor:
    """L_TV: the fit stage's grid regularisers of the deformation field (HexPlane TV, time
    smoothness, time L1) with its weights; ``lambda_tv`` overrides the TV weight. 0 for a
    static model."""
    d = pm.fit.deformation
    if d is None or not pm.fit.deforming:
        return pm.background.new_zeros(())
    fo = _fit_options(pm.fit)
    r = d.regularizers()
    w_tv = fo["plane_tv_weight"] if lambda_tv is None else lambda_tv
    return (w_tv * r["plane_tv"] + fo["time_smooth_weight"] * r["time_smooth"]
            + fo["time_l1_weight"] * r["time_l1"])


def _latest_checkpoint(ckdir):
    from pathlib import Path

    files = sorted(Path(ckdir).glob("ckpt_*.pt"))
    return files[-1] if files else None


# options that do not change the result: a checkpoint stays valid when they differ
_NON_RESULT_OPTIONS = ("iterations", "checkpoint_every", "log_every")


def run_key(opts: PartitionOptions, **inputs) -> dict:
    """What a checkpoint must match to be resumed from: the options that shape the result and
    fingerprints of the inputs (``inputs``: name -> str)."""
    import dataclasses

    d = {k: v for k, v in dataclasses.asdict(opts).items() if k not in _NON_RESULT_OPTIONS}
    return {**d, **{k: str(v) for k, v in inputs.items()}}


def _save_checkpoint(ckdir, it, pm, opt, index, rows, opts, key) -> None:
    from pathlib import Path

    from .io import atomic_path

    ckdir = Path(ckdir)
    blob = {"iteration": it, "pmodel": partition_blob(pm, opts), "optimizer": opt.state_dict(),
            "index": index.state_dict(), "log": rows, "key": key}
    with atomic_path(ckdir / f"ckpt_{it:06d}.pt") as tmp:
        torch.save(blob, tmp)
    for old in sorted(ckdir.glob("ckpt_*.pt"))[:-2]:  # keep the two newest
        old.unlink(missing_ok=True)


def _view_rng(seed: int, it: int, purpose: int) -> np.random.Generator:
    """Per-iteration random generator: training is reproducible and resumes exactly."""
    return np.random.default_rng([int(seed), int(it), int(purpose)])


def fine_tune(pm: PartitionModel, data: list[dict], opts: PartitionOptions, ckdir=None,
              extent: float = 1.0, key: dict | None = None) -> list[dict]:
    """Optimise ``pm`` on ``data``: L = L1 + L_TV + lambda_2d BCE + lambda_3d L3d.

    With ``opts.geometry_lr_scale`` = 0 (default) the fitted Gaussians are frozen: L1 and L_TV
    are then constants and are skipped, the blending weights of every training view are
    computed once (:func:`blend_weights`) and a step blends one number per Gaussian (the
    change logit) instead of rasterizing colour and features. With ``geometry_lr_scale`` > 0
    the fitted parameters are fine-tuned too and every step rasterizes colour + encodings.
    The BCE weighs each pixel by ``weight`` when a ``data`` item has one (see
    :func:`ignore_weight`) and is class balanced (:func:`bce_on_change_logit`) with
    ``opts.balance_classes``; the changed-pixel fraction is then taken over all targets.

    Args:
        pm: the model (modified in place; its device is used).
        data: one dict per training photo: ``camera`` (Camera), ``time`` (0/1), ``image``
            [H, W, 3] float tensor (sRGB), ``target`` [H, W] float tensor in [0, 1] and
            optionally ``weight`` [H, W] (per-pixel BCE weight, None = 1).
        opts: options (iterations, weights, learning rates, kNN settings, checkpointing).
        ckdir: checkpoint folder (``ckpt_NNNNNN.pt`` every ``checkpoint_every`` iterations and
            at the end, the two newest kept); training resumes from the newest one when its
            iteration is <= ``opts.iterations`` and its ``key`` matches.
        extent: scene extent (world units) scaling the position / deformation learning rates.
        key: :func:`run_key` of this run (default: from ``opts`` alone); a checkpoint with
            another key (other options or inputs) is ignored with a warning.
    Returns:
        the training log: one dict per ``log_every`` iterations (iteration, loss terms, seconds).
    Raises:
        gdiff.errors.TrainingError: the loss became NaN/inf (names iteration and checkpoint).
    """
    import time as _time
    from pathlib import Path

    from .errors import TrainingError
    from .log import progress
    from .splat.losses import l1

    if not data:
        raise ValueError("no training views")
    index = NeighbourIndex(opts.knn_k, opts.knn_samples, opts.knn_refresh, opts.seed)
    start, rows = 0, []
    key = run_key(opts) if key is None else key
    ck = _latest_checkpoint(ckdir) if ckdir is not None else None
    if ck is not None:
        try:
            blob = torch.load(ck, map_location="cpu", weights_only=True)
        except Exception as e:  # written atomically, so only a foreign/corrupt file
            log.warning("ignoring unreadable checkpoint %s (%s)", ck, e)
            blob = {"iteration": -1}
        if blob.get("key") != key or blob["iteration"] < 0:
            log.warning("checkpoint %s is from other options or inputs; starting afresh", ck)
            ck = None
        elif blob["iteration"] <= opts.iterations:
            _load_state(pm, blob["pmodel"])
            start, rows = int(blob["iteration"]), list(blob["log"])
            index.load_state_dict(blob["index"])
            log.info("resuming partition training from %s (iteration %d)", ck, start)
        else:
            ck = None
    pm.train()
    frozen = opts.geometry_lr_scale <= 0
    pos_fraction = (changed_fraction([v["target"] for v in data],
                                     [v.get("weight") for v in data])
                    if opts.balance_classes else None)
    opt = torch.optim.Adam(_param_groups(pm, opts, extent), eps=1e-15)
    if frozen:
        frozen_g, weights = _cache_weights(pm, data)
    if ck is not None:
        opt.load_state_dict(blob["optimizer"])
    last_ck = str(ck) if ck is not None else "none"
    acc = {"l1": 0.0, "tv": 0.0, "bce": 0.0, "l3d": 0.0, "n3d": 0}
    t0 = _time.perf_counter()
    for it in progress(range(start, opts.iterations), desc="partition", initial=start,
                       total=opts.iterations):
        vi = int(_view_rng(opts.seed, it, 0).integers(len(data)))
        v = data[vi]
        if frozen:
            g = frozen_g[float(v["time"])]
            z = blended_change_logit(pm.head, weights[vi])
            loss_bce = bce_on_change_logit(z, v["target"], pos_fraction, v.get("weight"))
            loss_l1 = loss_tv = loss_bce.new_full((), float("nan"))  # constants: not computed
            loss = opts.lambda_2d * loss_bce
        else:
            g = pm.fit.at_time(float(v["time"]))
            r = render_features(g, pm.head.encoding, v["camera"], pm.background, with_rgb=True)
            loss_l1 = l1(r["rgb"], v["image"])
            loss_tv = _tv_loss(pm, opts.lambda_tv)
            loss_bce = bce_on_change_logit(change_logit(pm.head.classify(r["features"])),
                                           v["target"], pos_fraction, v.get("weight"))
            loss = loss_l1 + loss_tv + opts.lambda_2d * loss_bce
        if opts.lambda_3d > 0 and it % opts.l3d_every == 0:
            s, nb = index.sample(g.means, rng=_view_rng(opts.seed, it, 1))
            loss_3d = neighbour_kl(pm.head.gaussian_logits(), s, nb)
            loss = loss + opts.lambda_3d * loss_3d
            acc["l3d"] += loss_3d.item()
            acc["n3d"] += 1
        if not torch.isfinite(loss):
            raise TrainingError(
                f"partition training diverged: loss is {loss.item()} at iteration {it} "
                f"(L1 {loss_l1.item():.4g}, BCE {loss_bce.item():.4g}); last checkpoint: "
                f"{last_ck}. Lower partition.lr_encoding / lr_head / geometry_lr_scale and "
                "rerun (training resumes from the checkpoint)")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        acc["l1"] += loss_l1.item()
        acc["tv"] += loss_tv.item()
        acc["bce"] += loss_bce.item()
        done = it + 1
        if done % opts.log_every == 0 or done == opts.iterations:
            n = done - (rows[-1]["iteration"] if rows else 0)
            rows.append({"iteration": done, "l1": acc["l1"] / n, "tv": acc["tv"] / n,
                         "bce": acc["bce"] / n,
                         "l3d": acc["l3d"] / acc["n3d"] if acc["n3d"] else float("nan"),
                         "seconds": _time.perf_counter() - t0})
            acc = {"l1": 0.0, "tv": 0.0, "bce": 0.0, "l3d": 0.0, "n3d": 0}
        if ckdir is not None and (done % opts.checkpoint_every == 0 or done == opts.iterations):
            _save_checkpoint(ckdir, done, pm, opt, index, rows, opts, key)
            last_ck = str(Path(ckdir) / f"ckpt_{done:06d}.pt")
    pm.eval()
    return rows


def _cache_weights(pm: PartitionModel, data: list[dict]):
    """Frozen geometry: the activated Gaussians per training time (no grad) and the
    :class:`BlendWeights` of every view in ``data`` (same order)."""
    import time as _time

    from .log import progress

    t0 = _time.perf_counter()
    with torch.no_grad():
        gs = {t: pm.fit.at_time(t) for t in sorted({float(v["time"]) for v in data})}
    weights = [blend_weights(gs[float(v["time"])], v["camera"])
               for v in progress(data, desc="partition weights")]
    log.info("blend weights of %d views: %.0f MB, %.1f s", len(data),
             sum(w.nbytes for w in weights) / 2**20, _time.perf_counter() - t0)
    return gs, weights


def _load_state(pm: PartitionModel, blob: dict) -> None:
    """Copy fitted parameters, encodings and head from a :func:`partition_blob` into ``pm``."""
    with torch.no_grad():
        pm.fit.load_state_dict(blob["fit"]["state_dict"])
        pm.head.load_state_dict(blob["head"])


def train_partition(fit_model_path, cameras_json, keyframes_csv, scene_dir, out_dir,
                    options: PartitionOptions | None = None, device="auto") -> dict:
    """The ``partition`` stage: fine-tune the fitted 4D model with change encodings.

    Args:
        fit_model_path: ``results/<scene>/fit/model.pt``.
        cameras_json: ``results/<scene>/poses/cameras.json`` (key images and eval views).
        keyframes_csv: ``results/<scene>/change/keyframes.csv`` (targets, see
            :func:`read_key_views`).
        scene_dir: the scene folder (photos).
        out_dir: ``results/<scene>/partition/``; receives ``model.pt``, ``changed.ply``,
            ``unchanged.ply`` (+ per-time ``changed_t0/_t1``, ``unchanged_t0/_t1`` PLYs),
            ``probability.npy`` (per-Gaussian change probability [N] float32),
            ``maps/`` (change maps at every key pose, see :func:`write_key_maps`),
            ``keypose_scores.csv``, ``train_log.csv``, ``summary.json``; ``ckpt/`` while
            training (removed when the stage completes; a rerun resumes from it).
        options: :class:`PartitionOptions` (defaults when None).
        device: ``auto``/``cpu``/``cuda``.
    Returns:
        summary dict (counts of Gaussians, mean key-pose IoU, seconds).
    """
    import shutil
    import time as _time
    from pathlib import Path

    import pandas as pd

    from .cameras import Camera
    from .device import resolve_device
    from .io import write_csv, write_json
    from .splat.gaussians import camera_extent
    from .splat.model import load_model

    opts = options or PartitionOptions()
    dev = resolve_device(device)
    out = Path(out_dir)
    t_start = _time.perf_counter()
    torch.manual_seed(opts.seed)
    fit = load_model(fit_model_path, dev)
    fo = _fit_options(fit)
    max_side = fo["max_side"] if opts.max_side is None else opts.max_side
    views = read_key_views(keyframes_csv, cameras_json, scene_dir, max_side)
    data = [{"camera": v.camera, "time": v.time,
             "image": torch.from_numpy(_load_image(v.image, v.camera)).to(dev),
             "target": torch.from_numpy(_load_mask(v.target, v.camera)).to(dev),
             "weight": (torch.from_numpy(ignore_weight(_load_mask(v.target, v.camera),
                                                       _load_mask(v.other, v.camera))).to(dev)
                        if opts.ignore_other_time else None)} for v in views]
    head = ChangeHead(len(fit), opts.encoding_dim, opts.seed)
    bg = [1.0, 1.0, 1.0] if fo["background"] == "white" else None  # random/black: black
    meta = getattr(fit, "meta", None) or {}
    cam0 = Camera(**meta["camera"]) if "camera" in meta else views[0].camera.with_pose(np.eye(4))
    pm = PartitionModel(fit, head, cam0, bg, opts.threshold).to(dev)
    extent = float(meta.get("extent") or camera_extent(
        np.stack([v.camera.center for v in views])))
    log.info("partition: %d Gaussians, %d key views, %d iterations on %s", len(fit), len(views),
             opts.iterations, dev)
    key = run_key(opts, fit=_sha1(fit_model_path), keyframes=_sha1(keyframes_csv),
                  cameras=_sha1(cameras_json))
    rows = fine_tune(pm, data, opts, out / "ckpt", extent, key)
    t_train = _time.perf_counter() - t_start
    save_partition_model(pm, out / "model.pt", opts)
    write_csv(out / "train_log.csv", pd.DataFrame(rows))
    prob = pm.gaussian_probability().detach().cpu().numpy().astype(np.float32)
    from .io import atomic_path

    with atomic_path(out / "probability.npy") as tmp:
        np.save(tmp, prob)
    counts = write_split_ply(pm, out, opts.threshold)
    scores = write_key_maps(pm, views, out / "maps")
    write_csv(out / "keypose_scores.csv", scores)
    summary = {"gaussians": len(fit), **counts, "key_views": len(views),
               "iterations": opts.iterations,
               "keypose_iou_own_time": float(np.nanmean(scores["iou_own_time"])),
               "keypose_iou_union": float(np.nanmean(scores["iou_union"])),
               "seconds_train": t_train, "seconds_total": _time.perf_counter() - t_start}
    write_json(out / "summary.json", summary)
    shutil.rmtree(out / "ckpt", ignore_errors=True)  # finished: nothing to resume
    log.info("partition done: %s", summary)
    return summary


def _sha1(path) -> str:
    import hashlib

    h = hashlib.sha1()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


# --------------------------------------------------------------------------------------------
# outputs


MIN_VISIBLE_OPACITY = 0.005  # a Gaussian below this opacity at time t is absent at t


@torch.no_grad()
def split_gaussians(pm: PartitionModel, t: float, threshold: float = 0.5):
    """Changed and unchanged Gaussians at time ``t`` (activated, deformed to ``t``).

    A Gaussian is changed when its probability ``softmax(Conv(e))[changed]`` exceeds
    ``threshold``; Gaussians whose opacity at ``t`` is below ``MIN_VISIBLE_OPACITY`` are absent
    at ``t`` (e.g. a removed object's Gaussians after the change) and left out.
    Returns (changed, unchanged) :class:`gdiff.splat.gaussians.Gaussians`.
    """
    g = pm.fit.at_time(float(t)).detach()
    p = pm.gaussian_probability()
    present = g.opacities >= MIN_VISIBLE_OPACITY
    return g.subset((p > threshold) & present), g.subset((p <= threshold) & present)


def write_split_ply(pm: PartitionModel, out_dir, threshold: float = 0.5) -> dict:
    """Write ``changed_t0/_t1.ply``, ``unchanged_t0/_t1.ply`` (3DGS layout) and
    ``changed.ply`` (the changed Gaussians present at t=0 followed by those present at t=1:
    what was there and changed plus what is new), ``unchanged.ply`` (= ``unchanged_t0``).
    Returns the Gaussian counts per file."""
    from pathlib import Path

    from .splat.gaussians import Gaussians
    from .splat.ply import write_gaussians

    out = Path(out_dir)
    parts, counts = {}, {}
    for t in (0, 1):
        parts[f"changed_t{t}"], parts[f"unchanged_t{t}"] = split_gaussians(pm, t, threshold)
    c0, c1 = parts["changed_t0"], parts["changed_t1"]
    parts["changed"] = Gaussians(*(torch.cat([getattr(c0, k), getattr(c1, k)])
                                   for k in ("means", "quats", "scales", "opacities", "sh")),
                                 sh_degree=c0.sh_degree)
    parts["unchanged"] = parts["unchanged_t0"]
    for name, g in parts.items():
        write_gaussians(out / f"{name}.ply", g)
        counts[f"n_{name}"] = len(g)
    return counts


def overlay(image: np.ndarray, mask: np.ndarray, colour=(1.0, 0.15, 0.1), alpha: float = 0.5,
            outline: np.ndarray | None = None) -> np.ndarray:
    """The image [H, W, 3] (float sRGB) with ``mask`` [H, W] tinted in ``colour`` and its
    outline drawn; ``outline`` (optional bool [H, W], e.g. a target mask) is drawn in green."""
    import cv2

    img = np.clip(np.asarray(image, np.float32), 0, 1).copy()
    m = np.asarray(mask, bool)
    img[m] = (1 - alpha) * img[m] + alpha * np.asarray(colour, np.float32)
    for mm, col in ((m, colour), (outline, (0.1, 1.0, 0.2))):
        if mm is None:
            continue
        cs, _ = cv2.findContours(np.asarray(mm, np.uint8), cv2.RETR_EXTERNAL,
                                 cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(img, cs, -1, tuple(float(c) for c in col), 1)
    return img


def write_key_maps(pm: PartitionModel, views: list[KeyView], maps_dir):
    """Render change maps at every key pose and score them against the compare-stage masks.

    Writes, per key view ``<name>`` (``<path>_<frame>``): ``maps/{t0,t1,union}/<name>.png``
    (binary masks, 255 = changed), ``maps/{t0,t1,union}_prob/<name>.png`` (probability x 255)
    and ``maps/overlay/<name>.png`` (the photo with the union map in red and the compare
    stage's union mask outlined in green). Returns a DataFrame with one row per view: name,
    time, IoU of the map at the photo's time vs its target (``iou_own_time``) and of the union
    map vs ``mask_union`` (``iou_union``), plus pixel F1 of the union.
    """
    from pathlib import Path

    import pandas as pd

    from .io import write_image, write_mask
    from .log import progress
    from .metrics import pixel_scores

    maps_dir = Path(maps_dir)
    rows = []
    for v in progress(views, desc="partition maps"):
        r = render_change_map(pm, v.camera, None)
        th = pm.threshold
        for key, p in (("t0", r["prob_t0"]), ("t1", r["prob_t1"]), ("union", r["prob"])):
            write_mask(maps_dir / key / f"{v.name}.png", p > th)
            write_image(maps_dir / f"{key}_prob" / f"{v.name}.png",
                        np.repeat(p[..., None], 3, axis=2))
        own = _load_mask(v.target, v.camera) > 0.5
        union_t = _load_mask(v.masks["union"], v.camera) > 0.5
        photo = _load_image(v.image, v.camera)
        write_image(maps_dir / "overlay" / f"{v.name}.png",
                    overlay(photo, r["mask"], outline=union_t))
        own_pred = r[f"prob_t{int(v.time)}"] > th
        s_own, s_union = pixel_scores(own_pred, own), pixel_scores(r["mask"], union_t)
        rows.append({"name": v.name, "image": str(v.image), "time": v.time,
                     "iou_own_time": s_own["IoU"], "iou_union": s_union["IoU"],
                     "f1_union": s_union["F1"]})
    return pd.DataFrame(rows)


# --------------------------------------------------------------------------------------------
# command line: gdiff change-map


def _read_c2w(path) -> np.ndarray:
    """A 4x4 (or 3x4) camera-to-world matrix from .npy, .json (a matrix, or an object with
    ``c2w`` / ``transform_matrix``) or a text file of 12/16 numbers."""
    import json
    from pathlib import Path

    from .errors import GdiffError

    path = Path(path)
    try:
        if path.suffix == ".npy":
            a = np.load(path)
        elif path.suffix == ".json":
            d = json.loads(path.read_text())
            a = d.get("c2w", d.get("transform_matrix")) if isinstance(d, dict) else d
            a = np.asarray(a, dtype=np.float64)
        else:
            a = np.loadtxt(path, dtype=np.float64)
    except (OSError, ValueError, TypeError) as e:
        raise GdiffError(f"{path}: cannot read a camera-to-world matrix ({e}); give a .npy, "
                         ".json or text file with a 4x4 matrix") from None
    return _as_c2w(np.asarray(a, dtype=np.float64), str(path))


def _as_c2w(a: np.ndarray, source: str) -> np.ndarray:
    from .errors import GdiffError

    a = a.reshape(-1)
    if a.size not in (12, 16) or not np.isfinite(a).all():
        raise GdiffError(f"{source}: expected 12 or 16 finite numbers (a 3x4 or 4x4 "
                         f"camera-to-world matrix, row-major), got {a.size}")
    m = a.reshape(-1, 4)
    return np.vstack([m, [0, 0, 0, 1]]) if len(m) == 3 else m


def pose_from_values(values: list[float]) -> np.ndarray:
    """c2w [4, 4] from 7 numbers ``x y z qw qx qy qz`` (camera centre in world units and the
    camera-to-world rotation as a wxyz quaternion, OpenCV camera axes) or 12/16 numbers (a
    row-major 3x4/4x4 c2w matrix)."""
    from scipy.spatial.transform import Rotation

    from .errors import GdiffError

    v = np.asarray(values, dtype=np.float64)
    if v.size == 7:
        q = v[3:]
        if not np.isfinite(v).all() or np.linalg.norm(q) < 1e-12:
            raise GdiffError("--pose: the quaternion qw qx qy qz must be finite and non-zero")
        c2w = np.eye(4)
        c2w[:3, :3] = Rotation.from_quat(q, scalar_first=True).as_matrix()
        c2w[:3, 3] = v[:3]
        return c2w
    return _as_c2w(v, "--pose")


def change_map_main(argv=None) -> int:
    """``gdiff change-map``: render a change map from a partition model at any camera pose."""
    import argparse

    from .cameras import Camera, load_cameras
    from .errors import GdiffError
    from .io import write_image, write_mask

    p = argparse.ArgumentParser(
        prog="gdiff change-map", description=change_map_main.__doc__,
        epilog="Camera axes are OpenCV (x right, y down, z forward); c2w is camera-to-world. "
               "Without intrinsics options the model's training intrinsics are used.")
    p.add_argument("--model", required=True, help="results/<scene>/partition/model.pt")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--c2w", metavar="FILE",
                     help="4x4 camera-to-world matrix (.npy, .json or text)")
    src.add_argument("--pose", nargs="+", type=float, metavar="V",
                     help="x y z qw qx qy qz (centre + c2w rotation), or 12/16 matrix numbers")
    src.add_argument("--cameras", metavar="JSON",
                     help="a cameras.json; with --frame, render that frame's camera")
    p.add_argument("--frame", default="0",
                   help="with --cameras: frame index or image path (default 0)")
    p.add_argument("--t", type=float, default=None,
                   help="time: 0 (before) or 1 (after); omitted = union of t=0 and t=1")
    p.add_argument("--out", required=True, help="binary change mask PNG (255 = changed)")
    p.add_argument("--prob-out", help="also write the change probability (PNG x255, or .npy)")
    p.add_argument("--image-out", help="also write the rendered image (PNG)")
    p.add_argument("--overlay-out", help="also write the image with the mask overlaid (PNG)")
    for k in ("width", "height"):
        p.add_argument(f"--{k}", type=int, help=f"image {k} (px)")
    for k in ("fx", "fy", "cx", "cy"):
        p.add_argument(f"--{k}", type=float, help=f"intrinsic {k} (px, pixel centres at +0.5)")
    p.add_argument("--device", default="auto", help="auto, cpu or cuda")
    args = p.parse_args(argv)

    pm = load_partition_model(args.model, args.device)
    cam = pm.camera
    if args.cameras:
        cams = load_cameras(args.cameras)
        sel = [c for c in cams if c.image == args.frame]
        if not sel:
            try:
                sel = [cams[int(args.frame)]]
            except (ValueError, IndexError):
                raise GdiffError(f"{args.cameras}: no frame {args.frame!r} (give an index "
                                 f"0..{len(cams) - 1} or an image path)") from None
        cam = sel[0]
    else:
        c2w = _read_c2w(args.c2w) if args.c2w else pose_from_values(args.pose)
        cam = cam.with_pose(c2w)
    if args.width or args.height:
        if not (args.width and args.height):
            raise GdiffError("--width and --height go together")
        s = args.width / cam.width
        cam = Camera(args.width, args.height, cam.fx * s, cam.fy * args.height / cam.height,
                     cam.cx * s, cam.cy * args.height / cam.height, cam.c2w)
    over = {k: getattr(args, k) for k in ("fx", "fy", "cx", "cy") if getattr(args, k)}
    if over:
        cam = Camera(cam.width, cam.height, **{**{k: getattr(cam, k) for k in
                                                   ("fx", "fy", "cx", "cy")}, **over},
                     c2w=cam.c2w)
    if args.t is not None and not 0.0 <= args.t <= 1.0:
        raise GdiffError(f"--t must lie in [0, 1] (0 = before, 1 = after), got {args.t}")
    want_img = bool(args.image_out or args.overlay_out)
    r = render_change_map(pm, cam, args.t, with_image=want_img)
    write_mask(args.out, r["mask"])
    if args.prob_out:
        if args.prob_out.endswith(".npy"):
            from .io import atomic_path

            with atomic_path(args.prob_out) as tmp:
                np.save(tmp, r["prob"])
        else:
            write_image(args.prob_out, np.repeat(r["prob"][..., None], 3, axis=2))
    if args.image_out:
        write_image(args.image_out, r["image"])
    if args.overlay_out:
        write_image(args.overlay_out, overlay(r["image"], r["mask"]))
    frac = float(r["mask"].mean())
    print(f"{args.out}: {cam.width}x{cam.height}, t={'union' if args.t is None else args.t}, "
          f"{100 * frac:.2f}% changed")
    return 0
