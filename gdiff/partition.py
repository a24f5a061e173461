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

    iterations: int = 3000            # fine-tuning steps (one training image per step)
    encoding_dim: int = 16            # length of the per-Gaussian classification encoding
    lambda_2d: float = 1.0            # weight of the BCE between rendered and target masks
    lambda_3d: float = 2.0            # weight of the kNN KL regulariser L3d
    knn_k: int = 5                    # neighbours per sampled Gaussian in L3d
    knn_samples: int = 1000           # Gaussians sampled per L3d evaluation (m)
    l3d_every: int = 2                # evaluate L3d every this many iterations
    knn_refresh: int = 200            # rebuild the KD-tree of centres every this many L3d calls
    lr_encoding: float = 0.0025       # Adam learning rate of the encodings
    lr_head: float = 0.0005           # Adam learning rate of the 1x1 convolution
    geometry_lr_scale: float = 0.1    # fit-stage learning rates are multiplied by this
    lambda_tv: float | None = None    # TV weight; None = the fit stage's value
    threshold: float = 0.5            # probability above which a pixel / Gaussian is "changed"
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


def mask_bce(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """The 2D loss: binary cross-entropy of the rendered change probability against a mask.

    Args:
        logits: [..., H, W, 2] rendered class logits.
        target: [..., H, W] mask (bool or float in [0, 1]; 1 = changed).
    Returns:
        scalar, mean over pixels (the paper's 1/|M| normalisation).
    """
    return F.binary_cross_entropy_with_logits(change_logit(logits), target.to(logits.dtype))


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
