"""Training losses of the partition stage: the 2D BCE between rendered change maps and masks
(optionally class balanced, with per-pixel weights) and the 3D kNN KL regulariser L3d.

Conventions: see :mod:`gdiff.partition`.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from ..knn import NeighbourIndex
from .head import ChangeHead, change_logit


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
    # index_select, not logp[idx]: its backward sums repeated rows in a fixed order, so a
    # training step is reproducible on several threads (CPU index_put accumulates do not)
    ls = logp.index_select(0, sample).unsqueeze(1)                                   # [m, 1, 2]
    ln = logp.index_select(0, neighbours.reshape(-1)).reshape(*neighbours.shape, -1)  # [m, k, 2]
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
