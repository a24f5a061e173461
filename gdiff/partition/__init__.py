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
* Two phases: the first ``frozen_iterations`` steps keep the fitted Gaussians frozen. The
  rasterizer is then linear in the features, so each key view's blending weights are computed
  once (:func:`blend_weights`, a sparse [H*W, N] matrix) and a step blends one change logit
  per Gaussian (:func:`blended_change_logit`, exact because the head is affine) instead of
  deforming the model and rasterizing colour + encodings forward and backward; L1 and L_TV
  are constants there. The encodings converge in this phase. The cache is what bounds the
  stage's memory, so it is kept compact: key views at their training size while the cache
  fits in ``cache_max_mb``, else at the scale whose pixels fit (targets area-averaged;
  ``frozen_scale`` fixes the scale), pairs grouped by pixel (a pair stores an int32 Gaussian
  index and a float16 weight), a pixel's faintest pairs dropped up to a small total weight,
  computed in bands of rows (bounded transient memory); it is released before the joint
  phase. With ``geometry_lr_scale`` > 0 the remaining steps fine-tune the fitted Gaussians too (the
  paper's total loss, at ``geometry_lr_scale`` x the fit's final learning rates), rasterizing
  colour + the 1-channel change logit, so Gaussians that straddle a changed object's outline
  adapt to the masks. That fits the key views' masks more closely, errors included: the
  compare stage's masks are not exact (a torus's hole, contact shadows, fragments), and
  Gaussians reshaped to follow them carry the errors to every other view, at about three
  times the cost of a frozen step. The default (``geometry_lr_scale`` 0) therefore keeps the
  fitted model frozen throughout and learns only the encodings and the head; the change maps
  then render from the fit's own geometry. With exact masks (a synthetic scene's ground
  truth) the joint phase sharpens the outlines instead.
* Map threshold (``threshold``): ``None`` (the default) keeps 0.5, the probability a
  BCE-trained head calls even, unless the probability threshold whose (ungated) union maps best
  reproduce the compare stage's union masks at the key views (max pooled F1 over a 0.01
  grid, :func:`choose_threshold`, after training) beats 0.5 there by more than
  ``threshold_gain`` F1 and reaches F1 0.5 there
  (:func:`~gdiff.partition.train.operating_point`). A head that could
  not fit its supervision (masks that disagree between views) so gets the threshold its own
  views call for, while a nearly flat curve does not move it: on noisy compare masks (false
  changes on poorly fitted surfaces) the maximum follows the noise. A number fixes the
  threshold. The value used, how it was chosen, the key-view best and the key-view F1 curve go
  to ``partition/threshold.json`` and the log.
* Union map (``before_gate``): the change map of a viewpoint with no time given is what is there
  now and is new (the t=1 map) plus what was there and changed (the t=0 map), the latter only
  where the two times render differently at the pixel (:mod:`.gate`). A before photo's mask
  covers the surface an added object hid from it, so those surface Gaussians are labelled
  changed although they are still there after; from another pose they show beside the object,
  where both times render the same. 0 keeps the plain per-pixel maximum, and so does a scene
  the compare stage took for a change of light (``light_changed`` in its keyframes.csv).

Modules: :mod:`.options` (``PartitionOptions``), :mod:`.head` (encodings + 1x1 conv),
:mod:`.losses` (BCE, L3d), :mod:`.render` (rasterized features, cached blend weights),
:mod:`.model` (``PartitionModel``, change maps, model.pt i/o), :mod:`.gate` (the union's
before-map gate), :mod:`.data` (key views),
:mod:`.train` (``fine_tune``, ``train_partition``), :mod:`.export` (PLY split, key-pose maps),
:mod:`.cli` (``gdiff change-map``). Their public names are importable from ``gdiff.partition``.

Conventions: cameras are :class:`gdiff.cameras.Camera` (OpenCV axes, c2w camera-to-world,
pixel centres at +0.5); time ``t`` in [0, 1] (before = 0, after = 1); probability maps are
float32 [H, W] in [0, 1]; masks bool [H, W] (written as 8-bit PNG, 255 = changed).
"""

from .cli import change_map_main, pose_from_values
from .data import KEYFRAME_COLUMNS, KeyView, _load_image, _load_mask, read_key_views
from .export import (MIN_VISIBLE_OPACITY, THRESHOLDS, choose_threshold, key_view_maps, overlay,
                     split_gaussians, write_key_maps, write_split_ply)
from .head import CHANGED, UNCHANGED, ChangeHead, change_logit, change_probability
from .losses import (bce_on_change_logit, changed_fraction, ignore_weight, l3d_step, mask_bce,
                     neighbour_disagreement, neighbour_kl)
from .model import (FORMAT, VERSION, PartitionModel, load_partition_model, partition_blob,
                    render_change_map, save_partition_model)
from .options import PartitionOptions
from .render import (BlendWeights, blend_weights, blended_change_logit, change_logit_parts,
                     render_blended, render_features)
from .train import fine_tune, operating_point, run_key, train_partition

__all__ = [
    "CHANGED", "FORMAT", "KEYFRAME_COLUMNS", "MIN_VISIBLE_OPACITY", "THRESHOLDS", "UNCHANGED",
    "VERSION",
    "BlendWeights", "ChangeHead", "KeyView", "PartitionModel", "PartitionOptions",
    "bce_on_change_logit", "blend_weights", "blended_change_logit", "change_logit",
    "choose_threshold", "key_view_maps",
    "change_logit_parts", "change_map_main", "change_probability", "changed_fraction",
    "fine_tune", "ignore_weight", "l3d_step", "load_partition_model", "mask_bce",
    "neighbour_disagreement", "neighbour_kl", "operating_point", "overlay", "partition_blob",
    "pose_from_values",
    "read_key_views", "render_blended", "render_change_map", "render_features", "run_key",
    "save_partition_model", "split_gaussians", "train_partition", "write_key_maps",
    "write_split_ply", "_load_image", "_load_mask",
]
