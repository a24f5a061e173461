"""Per-Gaussian change encodings and the 1x1 convolution that classifies them (paper Sec.
"4D Gaussian partition"); class logits -> change logit / probability.

Conventions: see :mod:`gdiff.partition`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


UNCHANGED, CHANGED = 0, 1


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
