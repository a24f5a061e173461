"""Options of the ``partition`` stage (config section ``partition``).

Conventions: see :mod:`gdiff.partition`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

log = logging.getLogger("gdiff.partition")


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
    geometry_lr_scale: float = 0.0    # x the fit's final learning rates in the joint phase
                                      # (0 = the fitted Gaussians stay frozen: see the
                                      # package docstring for why that is the default)
    frozen_iterations: int = 400      # first steps with the fitted Gaussians frozen (cached blend
                                      # weights: fast); later steps also fine-tune them with
                                      # L1 + L_TV (render every step). >= iterations or
                                      # geometry_lr_scale 0 = frozen throughout
    frozen_scale: float | None = None  # size of the key views in the frozen phase relative to
                                      # the training size (cached blend weights: 0.5 = a quarter
                                      # of the pixels, of the memory and of the time per step);
                                      # None = the training size when the cache fits in
                                      # cache_max_mb, else the scale at which it does
    cache_max_mb: float = 1024.0      # memory the cached blend weights may take when
                                      # frozen_scale is None (MB)
    lambda_tv: float | None = None    # weight of the HexPlane TV; None = the fit stage's value
    threshold: float | None = None    # probability above which a pixel / Gaussian is "changed";
                                      # None = from the key views: 0.5 unless the threshold that
                                      # best reproduces their masks gains more than
                                      # threshold_gain F1 there and reaches F1 0.5
                                      # (partition/threshold.json)
    threshold_gain: float = 0.01      # see threshold
    before_gate: float = 0.95         # the t=0 map counts in the union map only where the two
                                      # times' renders differ by more than this quantile of
                                      # their difference over the view's unchanged pixels
                                      # (gdiff.partition.gate); 0 = plain union
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
        if self.threshold is not None and not 0.0 < self.threshold < 1.0:
            raise ValueError("threshold must lie in (0, 1), or be null (chosen from the key "
                             "views)")
        if not 0.0 <= self.threshold_gain < 1.0:
            raise ValueError("threshold_gain must lie in [0, 1)")
        if not 0.0 <= self.before_gate < 1.0:
            raise ValueError("before_gate must lie in [0, 1) (0 = no gate)")
        if self.lambda_2d < 0 or self.lambda_3d < 0:
            raise ValueError("lambda_2d and lambda_3d must be >= 0")
        if self.max_side is not None and self.max_side < 0:
            raise ValueError("max_side must be >= 0 (0 = full resolution)")
        if self.frozen_iterations < 0 or self.geometry_lr_scale < 0:
            raise ValueError("frozen_iterations and geometry_lr_scale must be >= 0")
        if self.frozen_scale is not None and not 0.0 < self.frozen_scale <= 1.0:
            raise ValueError("frozen_scale must lie in (0, 1] (or be null)")
        if not self.cache_max_mb > 0:
            raise ValueError("cache_max_mb must be > 0")
        if self.checkpoint_every < 1 or self.log_every < 1:
            raise ValueError("checkpoint_every and log_every must be >= 1")
