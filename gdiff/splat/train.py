"""Fit one 4D Gaussian Splatting model to the before (t=0) and after (t=1) images.

Workflow entry point::

    from gdiff.splat.train import FitOptions, fit_scene
    summary = fit_scene(scene_dir, "results/S/poses/cameras.json", "results/S/poses/points.ply",
                        "results/S/fit", FitOptions(...), device="auto")

Training (after Wu et al., CVPR 2024, "4D Gaussian Splatting"):

1. Gaussians start at the SfM points (colour from the points, isotropic scale from the RMS
   distance to the 3 nearest neighbours, at most ``init_max_scale`` x extent, opacity
   ``init_opacity``).
2. Coarse phase (``coarse_iters``): static 3D Gaussians on all before and after images, except
   that each Gaussian's opacity may differ between the times (``splats["dopacity"]``, see
   :mod:`gdiff.splat.model`): an object that exists at one time only is kept opaque there and
   transparent at the other time instead of being blended into a half-transparent compromise.
   It renders at 1/``coarse_downscale`` of the working size: the first iterations, with few
   large Gaussians that overlap everywhere, are the most expensive per pixel, and coarse
   geometry and colour need no full-size images.
3. Fine phase (``fine_iters``): the HexPlane deformation field is switched on (its box set to
   the Gaussians' extent) and trained with the Gaussians; each image is rendered at its time.

Per-Gaussian changes over time (``dopacity``, ``dsh0``, ``dshN``; see
:mod:`gdiff.splat.model`) are learnt only for Gaussians in view (centre inside the image, any
opacity) in at least ``time_min_views`` training *renders* of *each* time; the others keep one
state for both times. The count is of renders over the whole fit, not of distinct photos:
every photo is rendered once per epoch, so a Gaussian in view of a single photo of a time
passes 2 after two epochs. What the gate asks is thus "seen by some photo of each time".
Before and after images are often taken from different places (other heights, other sides),
and a part of the scene seen at one time only carries no evidence of how it looks at the
other: with the change terms free, every update from the time that sees it moves the
shared value and the change term in opposite directions (for both parameters Adam takes
steps of the same size), so the other time keeps its initial (after an opacity reset:
transparent) state and novel views at that time show holes. Gating the terms lets the shared
parameters take the whole update instead ("no change without evidence"). Two photos per
time would locate a change in 3D, but a sparse capture sees many parts of its added objects
from a single photo of each time, so the gate asks only that each time saw it at all. The
counts (``DensifyStats.seen``) are kept for the whole fit and inherited by clones and split
children; the saved model has the gate folded in. ``time_change_weight`` adds the mean
absolute opacity change (``dopacity``, logit units, over the Gaussians whose change is
learnt) to the loss: without it a change costs nothing, and each time's images take
Gaussians of their own wherever they are fitted a little better so. The two renders of one
pose then differ in fine detail all over the scene, which the comparison must tell from a
change; with it the times share their Gaussians, and an opacity changes where the images of
the two times disagree. The default is a light price; even so it can weaken the change of a
small, far object, and a much higher one does so more. With ``time_change_scale`` s > 0 each
Gaussian pays s log(1 + |dopacity| / s) instead: as much as before for a small change, but a
whole change (an object there at one time only) costs little more than a half one, so the
price takes the small changes that let each time keep Gaussians of its own while leaving an
object that the photos show at one time only free to vanish at the other.

Each iteration renders one training image at the working resolution (``max_side``); every
image is used once per epoch, before and after images alternating (random order within a
time), so both states get the same share of the updates at every stage. Loss = L1 +
``ssim_lambda`` (1 - SSIM) + grid regularisers (fine phase). Over the default black
``background`` the fit may draw a dark surface (a shaded box front, the gap under a sofa)
half-transparent, the black showing through; the segmenter gives such pixels no ID below
``segment.alpha_min``. ``random`` (a new colour every step, as in nerfstudio's splatfacto)
renders nearly opaque, but its change maps were worse on a sparse real capture and on the
bench scenes with moved hard shadows (tried, not the default). 3DGS adaptive density control
runs every ``densify_every`` iterations between ``densify_from`` and ``densify_until``
(global iteration numbers), with thresholds scaled to the scene extent (camera spread); a
Gaussian's mean view-space gradient is taken over the views
of the times at which it exists (opacity above ``prune_opacity``), so Gaussians of an object
seen at one time only grow as readily as the others; pruning keeps a Gaussian that is opaque at
any time. Growth stops at ``max_gaussians`` (the cost of a step is about linear in the number
of Gaussians). Opacities are reset every ``opacity_reset_every``; for ``reset_hold`` iterations
after a reset the deformation field can be held (learning rates 0): the darkened image drives
its shared opacity and scale outputs up for every Gaussian at once, and at some seeds the field
runs away until the fit diverges or prunes most Gaussians at the next refine. The hold is off
by default (it also costs the change maps a little); a fit that diverges after a reset says
so and names it. The SH degree rises by one every ``sh_degree_interval`` iterations up to
``sh_degree``. The position learning rate decays exponentially over the whole run, the
deformation's over the fine phase.

Outputs in ``out_dir``: ``model.pt``, ``gaussians_t0.ply``, ``gaussians_t1.ply``,
``train_log.csv`` (iteration, phase, loss terms, PSNR of the step's image, #Gaussians,
seconds), ``quality.csv`` (per training image: PSNR, SSIM at the working resolution, and with
both times ``psnr_other_time``, see :func:`evaluate_views`) and
``ckpt/last.pt`` while training (everything needed to resume: parameters, optimiser state,
densification statistics, RNG states, iteration, log rows; written atomically every
``checkpoint_every`` iterations and removed after a successful fit). Rerunning after an
interruption resumes from it when the options and inputs are unchanged.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import pandas as pd
import torch

from ..cameras import TRAIN_SETS, Camera, image_root, load_cameras
from ..device import resolve_device
from ..errors import SceneError, TrainingError
from ..io import read_image, remove_stale_temporaries, save_torch, write_csv
from ..log import progress
from .deform import DeformConfig
from .exposure import ExposureCorrection, affine_colour_match
from .gaussians import DensifyStats, DensifyThresholds, camera_extent, refine, reset_opacity
from .losses import l1, psnr, ssim
from .model import GaussianModel4D, save_model
from .ply import read_points, write_gaussians
from .render import rasterize_gaussians

log = logging.getLogger("gdiff.splat.train")

CKPT_FORMAT = "gdiff.fit-checkpoint"
# options that do not change the result (a checkpoint stays valid when they change)
_NON_RESULT_OPTIONS = ("checkpoint_every", "log_every", "keep_checkpoint")


@dataclass
class FitOptions:
    """Options of the ``fit`` stage (config section ``fit``)."""

    # schedule
    coarse_iters: int = 300  # static phase on all images (opacity, colour may change over t)
    fine_iters: int = 1200  # phase with the deformation field
    max_side: int = 320  # working resolution: longest image side in px (0 = native size)
    coarse_downscale: int = 2  # the coarse phase renders at 1/k of the working size (1 = off)
    seed: int = 0
    # loss
    ssim_lambda: float = 0.2  # loss = L1 + ssim_lambda * (1 - SSIM) + regularisers
    plane_tv_weight: float = 0.0002  # TV of the HexPlane spatial planes
    time_smooth_weight: float = 0.001  # 2nd difference along t (needs time_resolution >= 3)
    time_l1_weight: float = 0.0001  # |1 - time plane|: prefer no change over time
    time_change_weight: float = 0.001  # mean |dopacity|: prefer Gaussians shared by the times
    # > 0: each Gaussian's price is s log(1 + |dopacity| / s) (logit units), as |dopacity| for a
    # small change but growing only logarithmically for a whole one (model.opacity_change)
    time_change_scale: float = 0.0
    background: str = "black"  # black | white | random (random colour per step)
    # learning rates (means: x scene extent, exponential decay over the run)
    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacities: float = 5e-2
    lr_dopacity: float = 5e-2  # per-Gaussian opacity change over time (logit units)
    lr_dsh0: float = 2.5e-3  # per-Gaussian diffuse colour change over time
    lr_sh0: float = 2.5e-3
    lr_shN: float = 1.25e-4
    lr_dshN: float = 1.25e-4  # per-Gaussian view-dependent colour change over time
    lr_grid: float = 1e-2  # HexPlane planes (normalised coordinates), decays over fine phase
    lr_grid_final: float = 1e-3
    lr_deform: float = 1e-3  # deformation MLP (x scene extent), decays over fine phase
    lr_deform_final: float = 1e-4
    # mirror-direction reflection (glare, highlights; gdiff.splat.reflection)
    reflection: bool = True  # add the shared-environment specular term (glare, highlights)
    reflection_height: int = 16  # rows of each environment map (width 2x)
    lr_reflectivity: float = 5e-2  # per-Gaussian reflection strength (logit)
    lr_environment: float = 3e-2  # environment maps (softplus radiance)
    # per-image colour correction (auto exposure / white balance; gdiff.splat.exposure)
    exposure: bool = False  # learn an affine colour transform per training image
    exposure_weight: float = 1e-2  # pull of each transform towards the identity
    lr_exposure: float = 1e-2
    # spherical harmonics
    sh_degree: int = 3
    sh_degree_interval: int = 375  # raise the active degree every N iterations (3 at 1125)
    # adaptive density control (iterations are global: coarse then fine)
    init_opacity: float = 0.1
    init_max_scale: float = 0.05  # largest initial Gaussian scale, x extent
    densify_from: int = 200
    densify_until: int = 1000
    densify_every: int = 100
    opacity_reset_every: int = 600  # 0 = never
    reset_hold: int = 0  # iterations after an opacity reset with the deformation field held
    grow_grad2d: float = 0.0002
    grow_scale3d: float = 0.01  # x extent
    prune_opacity: float = 0.005
    prune_scale3d: float = 0.1  # x extent
    prune_scale2d: float = 0.15  # x image size
    max_gaussians: int = 50000  # growth stops here (step cost is about linear in it)
    # deformation field
    time_opacity: bool = True  # per-Gaussian opacity change over time (splats "dopacity")
    time_color: bool = False  # per-Gaussian diffuse colour change over time (splats "dsh0")
    time_specular: bool = True  # per-Gaussian view-dependent colour change (splats "dshN")
    time_min_views: int = 2  # renders per time (not distinct photos) that must see a Gaussian
    # to learn its changes (0: all); see the module docstring
    deform: bool = True
    deform_position: bool = True
    deform_scale: bool = True
    deform_rotation: bool = True
    deform_opacity: bool = True  # lighting / appearance differ between before and after
    deform_color: bool = True
    hexplane_resolution: list[int] = field(default_factory=lambda: [48, 48, 48])
    hexplane_time_resolution: int = 2
    hexplane_multires: list[int] = field(default_factory=lambda: [1, 2])
    hexplane_features: int = 16
    deform_color_degree: int = 0  # SH degree changed by the colour head (0: diffuse colour)
    deform_width: int = 32  # MLP width
    deform_depth: int = 2  # layers of the shared MLP trunk
    deform_head_layers: int = 0  # hidden layers per head (4DGS: 1; costs ~10x more)
    # bookkeeping
    checkpoint_every: int = 500
    keep_checkpoint: bool = False
    log_every: int = 10
    backend: str = "auto"  # rasterizer backend: auto | torch | cpp | gsplat

    def last_opacity_reset(self, it: int) -> int | None:
        """The latest opacity reset at or before iteration count ``it``, or None: a reset
        follows each iteration count that is a multiple of ``opacity_reset_every`` and below
        ``densify_until``."""
        r = self.opacity_reset_every
        if r <= 0:
            return None
        last = min(it, self.densify_until - 1) // r * r
        return last if last >= r else None

    def __post_init__(self):
        if self.coarse_downscale < 1:
            raise ValueError(f"coarse_downscale must be >= 1, got {self.coarse_downscale}")
        for name in ("coarse_iters", "fine_iters", "max_side", "densify_every", "log_every",
                     "checkpoint_every", "sh_degree_interval", "max_gaussians",
                     "opacity_reset_every", "reset_hold", "time_min_views",
                     "time_change_weight", "time_change_scale"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.coarse_iters + self.fine_iters < 1:
            raise ValueError("coarse_iters + fine_iters must be at least 1")
        if not 0 <= self.sh_degree <= 3:
            raise ValueError(f"sh_degree must be 0..3, got {self.sh_degree}")
        if not 0.0 <= self.ssim_lambda <= 1.0:
            raise ValueError(f"ssim_lambda must be in [0, 1], got {self.ssim_lambda}")
        if self.background not in ("black", "white", "random"):
            raise ValueError(f"background must be black, white or random, got {self.background!r}")
        if self.hexplane_time_resolution < 2:
            raise ValueError("hexplane_time_resolution must be >= 2")
        if self.reflection_height < 2:
            raise ValueError(f"reflection_height must be >= 2, got {self.reflection_height}")
        if len(self.hexplane_resolution) != 3:
            raise ValueError("hexplane_resolution needs 3 values (x, y, z)")

    @property
    def total_iters(self) -> int:
        return self.coarse_iters + self.fine_iters

    def deform_config(self) -> DeformConfig | None:
        if not self.deform or self.fine_iters == 0:
            return None
        return DeformConfig(resolution=list(self.hexplane_resolution),
                            time_resolution=self.hexplane_time_resolution,
                            multires=list(self.hexplane_multires),
                            features=self.hexplane_features, width=self.deform_width,
                            depth=self.deform_depth, head_layers=self.deform_head_layers,
                            position=self.deform_position,
                            scale=self.deform_scale, rotation=self.deform_rotation,
                            opacity=self.deform_opacity, color=self.deform_color,
                            color_degree=self.deform_color_degree)

    def thresholds(self) -> DensifyThresholds:
        return DensifyThresholds(self.grow_grad2d, self.grow_scale3d, self.prune_opacity,
                                 self.prune_scale3d, self.prune_scale2d, self.max_gaussians)


# ------------------------------------------------------------------------------ data


@dataclass
class TrainView:
    """One training image at the working resolution: image [H, W, 3] in [0, 1] (device).

    ``small`` optionally holds the same view downscaled (image [h, w, 3], K [1, 3, 3]) for the
    coarse phase (see ``FitOptions.coarse_downscale``).
    """

    camera: Camera
    image: torch.Tensor
    viewmat: torch.Tensor  # [1, 4, 4] world-to-camera
    K: torch.Tensor  # [1, 3, 3]
    small: tuple[torch.Tensor, torch.Tensor] | None = None

    @property
    def time(self) -> float:
        return float(self.camera.time)

    def at_scale(self, coarse: bool) -> tuple[torch.Tensor, torch.Tensor]:
        """(image, K) to train on: the downscaled pair in the coarse phase when there is one."""
        if coarse and self.small is not None:
            return self.small
        return self.image, self.K


def working_scale(width: int, height: int, max_side: int) -> float:
    """Factor that brings the longest side down to ``max_side`` (1 when already small)."""
    if max_side <= 0 or max(width, height) <= max_side:
        return 1.0
    return max_side / float(max(width, height))


def load_views(scene_dir: str | Path, cameras: list[Camera], max_side: int,
               device: torch.device, downscale: int = 1) -> list[TrainView]:
    """Read the images of ``cameras`` (paths relative to ``scene_dir``) at the working size
    (and, with ``downscale`` > 1, also at 1/downscale of it, area-averaged).

    An image whose size differs from its camera's (same aspect) rescales the camera; a
    different aspect ratio is a :class:`SceneError`.
    """
    views = []
    for cam in cameras:
        if not cam.image:
            raise SceneError(f"camera of set {cam.set} has no image path in cameras.json")
        path = Path(scene_dir) / cam.image
        img = read_image(path)
        h, w = img.shape[:2]
        if (w, h) != (cam.width, cam.height):
            if abs(w / h - cam.width / cam.height) > 0.01:
                raise SceneError(f"{path}: image is {w}x{h} but cameras.json says "
                                 f"{cam.width}x{cam.height}; rerun the poses stage")
            cam = cam.scaled(w / cam.width)
        s = working_scale(w, h, max_side)
        if s != 1.0:
            cam = cam.scaled(s)
            img = cv2.resize(img, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
        t = lambda a: torch.tensor(a, dtype=torch.float32, device=device)[None]  # noqa: E731
        small = None
        if downscale > 1:
            lo = cam.scaled(1.0 / downscale)
            img_lo = cv2.resize(img, (lo.width, lo.height), interpolation=cv2.INTER_AREA)
            small = (torch.from_numpy(np.ascontiguousarray(img_lo)).to(device), t(lo.K))
        views.append(TrainView(cam, torch.from_numpy(np.ascontiguousarray(img)).to(device),
                               t(cam.w2c), t(cam.K), small))
    return views


def _fingerprint(*paths: Path) -> str:
    h = hashlib.sha1()
    for p in paths:
        h.update(Path(p).read_bytes())
    return h.hexdigest()


# ------------------------------------------------------------------------------ trainer


def _exp_lr(step: int, n: int, lr0: float, lr1: float) -> float:
    """Log-linear interpolation from lr0 (step 0) to lr1 (step n)."""
    if n <= 0:
        return lr1
    a = min(max(step / n, 0.0), 1.0)
    return math.exp((1 - a) * math.log(lr0) + a * math.log(lr1))


class Trainer:
    """Training state of one fit: model, optimiser, density statistics, RNG, log.

    ``step()`` runs one iteration; ``state_dict()`` / ``load_state_dict()`` (de)serialise it
    for checkpoints. The model and its densification can be reused by later stages.
    """

    def __init__(self, model: GaussianModel4D, views: list[TrainView], opts: FitOptions,
                 extent: float):
        self.model = model
        self.views = views
        self.opts = opts
        self.extent = float(extent)
        self.device = model.device
        self.iteration = 0  # next iteration to run
        self.times = sorted({v.time for v in views})
        self.exposure = ExposureCorrection(len(views)).to(self.device) if opts.exposure else None
        self.optimizer = self._make_optimizer()
        self.stats = DensifyStats(len(model), self.device, len(self.times))
        self.gen = torch.Generator().manual_seed(opts.seed)
        self.order = self._epoch_order()
        self.cursor = 0
        self.rows: list[dict] = []
        self.elapsed = 0.0

    # ---------------------------------------------------------------- optimiser
    def _make_optimizer(self) -> torch.optim.Optimizer:
        o, m = self.opts, self.model
        lrs = {"means": o.lr_means * self.extent, "scales": o.lr_scales, "quats": o.lr_quats,
               "opacities": o.lr_opacities, "dopacity": o.lr_dopacity, "sh0": o.lr_sh0,
               "dsh0": o.lr_dsh0, "shN": o.lr_shN, "dshN": o.lr_dshN,
               "reflectivity": o.lr_reflectivity}
        groups = [{"params": [p], "lr": lrs.get(name, o.lr_sh0), "name": name}
                  for name, p in m.splats.items()]
        if m.deformation is not None:
            groups.append({"params": m.deformation.grid_parameters(), "lr": o.lr_grid,
                           "name": "grid"})
            groups.append({"params": m.deformation.mlp_parameters(),
                           "lr": o.lr_deform * self.extent, "name": "deform"})
        if m.environment is not None:
            groups.append({"params": list(m.environment.parameters()), "lr": o.lr_environment,
                           "name": "environment"})
        if self.exposure is not None:
            groups.append({"params": list(self.exposure.parameters()), "lr": o.lr_exposure,
                           "name": "exposure"})
        return torch.optim.Adam(groups, lr=0.0, eps=1e-15, fused=self.device.type in ("cpu", "cuda"))

    def _set_lrs(self, it: int) -> None:
        o = self.opts
        fine_step = it - o.coarse_iters
        held = self.deformation_held(it)
        for g in self.optimizer.param_groups:
            if g["name"] == "means":
                g["lr"] = _exp_lr(it, o.total_iters, o.lr_means * self.extent,
                                  o.lr_means_final * self.extent)
            elif g["name"] == "grid":
                g["lr"] = 0.0 if held else _exp_lr(fine_step, o.fine_iters, o.lr_grid,
                                                   o.lr_grid_final)
            elif g["name"] == "deform":
                g["lr"] = 0.0 if held else _exp_lr(fine_step, o.fine_iters,
                                                   o.lr_deform * self.extent,
                                                   o.lr_deform_final * self.extent)

    def deformation_held(self, it: int) -> bool:
        """Whether iteration ``it`` (0-based, the one about to run) lies within ``reset_hold``
        iterations after an opacity reset (:meth:`FitOptions.last_opacity_reset`)."""
        last = self.opts.last_opacity_reset(it)
        return last is not None and it - last < self.opts.reset_hold

    # ---------------------------------------------------------------- phases
    def phase(self, it: int | None = None) -> str:
        it = self.iteration if it is None else it
        return "coarse" if it < self.opts.coarse_iters else "fine"

    @torch.no_grad()
    def start_fine(self) -> None:
        """Switch the deformation on, with its box fitted to the current Gaussians."""
        m = self.model
        if m.deformation is None or bool(m.deform_on):
            return
        means = m.splats["means"].detach()
        lo = torch.quantile(means, 0.005, dim=0) if len(means) > 1 else means.min(0).values
        hi = torch.quantile(means, 0.995, dim=0) if len(means) > 1 else means.max(0).values
        pad = 0.05 * (hi - lo).clamp_min(1e-3)
        m.deformation.field.set_aabb(lo - pad, hi + pad)
        m.deform_on.fill_(True)
        log.info("fine phase: deformation on, box %s .. %s", lo.tolist(), hi.tolist())

    def _epoch_order(self) -> torch.Tensor:
        """Every view once, times alternating (t0, t1, t0, ...; random order within a time)
        so both states get the same share of every stretch of iterations; the views of the
        larger set that are left over come last."""
        by_time: dict[float, list[int]] = {}
        for i, v in enumerate(self.views):
            by_time.setdefault(v.time, []).append(i)
        queues = [torch.tensor(ix)[torch.randperm(len(ix), generator=self.gen)].tolist()
                  for _, ix in sorted(by_time.items())]
        order = []
        for k in range(max(len(q) for q in queues)):
            order += [q[k] for q in queues if k < len(q)]
        return torch.tensor(order, dtype=torch.long)

    def _next_view(self) -> tuple[int, TrainView]:
        """(index into ``views``, view) of the next training image."""
        if self.cursor >= len(self.order):
            self.order = self._epoch_order()
            self.cursor = 0
        i = int(self.order[self.cursor])
        self.cursor += 1
        return i, self.views[i]

    def _background(self) -> torch.Tensor | None:
        b = self.opts.background
        if b == "black":
            return None
        if b == "white":
            return torch.ones(3, device=self.device)
        return torch.rand(3, generator=self.gen).to(self.device)

    @torch.no_grad()
    def effective_opacity_scale(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Largest opacity [N] and largest axis scale [N] over the training times."""
        opa = scale = None
        gate = self.time_gate()
        for t in self.times:
            g = self.model.at_time(t, gate)
            o, s = g.opacities, g.scales.max(dim=-1).values
            opa = o if opa is None else torch.maximum(opa, o)
            scale = s if scale is None else torch.maximum(scale, s)
        return opa, scale

    def time_gate(self) -> torch.Tensor | None:
        """[N] float, 1 for the Gaussians whose own change over time is learnt: those seen in
        at least ``time_min_views`` training views of every time (None: no gate)."""
        if self.opts.time_min_views <= 0 or len(self.times) < 2:
            return None
        return self.stats.seen_at_all_times(self.opts.time_min_views).float()

    # ---------------------------------------------------------------- one iteration
    def step(self) -> dict:
        o, m = self.opts, self.model
        it = self.iteration
        if it >= o.coarse_iters:
            self.start_fine()
        if o.sh_degree_interval and it > 0 and it % o.sh_degree_interval == 0:
            if int(m.active_sh_degree) < min(o.sh_degree, m.sh_degree):
                m.active_sh_degree += 1
        self._set_lrs(it)
        index, view = self._next_view()
        image, K = view.at_scale(it < o.coarse_iters)
        gate = self.time_gate()  # this step's: the render and the change price use one
        g = m.at_time(view.time, gate)
        h, w = image.shape[:2]
        colors, _, meta = rasterize_gaussians(g, view.viewmat, K, w, h, self._background(),
                                              "RGB", o.backend)
        self.stats.observe(meta["radii"], self.times.index(view.time), meta["means2d"], w, h)
        means2d = meta["means2d"]
        densify_now = o.densify_from <= it < o.densify_until and o.densify_every > 0
        if densify_now and means2d.requires_grad:
            means2d.retain_grad()
        pred = colors[0]
        terms = {}
        if self.exposure is not None:
            pred = self.exposure(pred, index)
            terms["exposure"] = self.exposure.regularizer(index)
        loss_l1 = l1(pred, image)
        loss_ssim = 1.0 - ssim(pred, image)
        loss = loss_l1 + o.ssim_lambda * loss_ssim
        if self.exposure is not None:
            loss = loss + o.exposure_weight * terms["exposure"]
        if m.deforming:
            terms.update(m.deformation.regularizers())
            loss = loss + (o.plane_tv_weight * terms["plane_tv"]
                           + o.time_smooth_weight * terms["time_smooth"]
                           + o.time_l1_weight * terms["time_l1"])
        change = (m.opacity_change(gate, o.time_change_scale) if o.time_change_weight > 0
                  else None)
        if change is not None:
            terms["time_change"] = change
            loss = loss + o.time_change_weight * change
        if not torch.isfinite(loss):
            raise FloatingPointError(f"loss is {float(loss.detach())}")
        loss.backward()
        if densify_now and means2d.grad is not None:
            # a Gaussian absent at this time (opacity ~0) is not judged on this view
            present = g.opacities.detach() > o.prune_opacity
            self.stats.update(means2d.grad, meta["radii"], w, h, present)
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        self.iteration = it + 1
        done = self.iteration
        event = None
        if densify_now and done % o.densify_every == 0 and done > o.densify_from:
            event = refine(m.splats, self.optimizer, self.stats, o.thresholds(), self.extent,
                           self.effective_opacity_scale,
                           prune_large=o.opacity_reset_every > 0 and done > o.opacity_reset_every)
        if o.last_opacity_reset(done) == done:
            reset_opacity(m.splats, self.optimizer, 2.0 * o.prune_opacity)
        out = {"iteration": done, "phase": self.phase(it), "loss": float(loss.detach()),
               "l1": float(loss_l1.detach()), "ssim": 1.0 - float(loss_ssim.detach()),
               "psnr": float(psnr(pred.detach().clamp(0, 1), image)),
               **{k: float(v.detach()) for k, v in terms.items()}, "n_gaussians": len(m)}
        if event is not None:
            out["densify"] = event
        return out

    # ---------------------------------------------------------------- checkpoints
    def state_dict(self) -> dict:
        return {
            "format": CKPT_FORMAT,
            "iteration": self.iteration,
            "model_config": self.model.config(),
            "model": {k: v.detach().clone() for k, v in self.model.state_dict().items()},
            "exposure": (None if self.exposure is None else
                         {k: v.detach().clone() for k, v in self.exposure.state_dict().items()}),
            "optimizer": self.optimizer.state_dict(),
            "densify": {k: v.clone() for k, v in self.stats.state_dict().items()},
            "rng_torch": torch.get_rng_state(),
            "rng_sampler": self.gen.get_state(),
            "order": self.order.clone(),
            "cursor": self.cursor,
            "rows": list(self.rows),
            "elapsed": self.elapsed,
        }

    def load_state_dict(self, st: dict) -> None:
        self.model = _drop_time_terms(GaussianModel4D.from_state(st["model_config"], st["model"]),
                                      self.opts).to(self.device)
        if self.exposure is not None:
            self.exposure.load_state_dict(st["exposure"])
        self.optimizer = self._make_optimizer()
        self.optimizer.load_state_dict(st["optimizer"])
        self.stats = DensifyStats(0, self.device)
        self.stats.load_state_dict({k: v.to(self.device) for k, v in st["densify"].items()})
        torch.set_rng_state(st["rng_torch"])
        self.gen.set_state(st["rng_sampler"])
        self.order = st["order"]
        self.cursor = int(st["cursor"])
        self.rows = list(st["rows"])
        self.elapsed = float(st["elapsed"])
        self.iteration = int(st["iteration"])


def _drop_time_terms(model: GaussianModel4D, opts: FitOptions) -> GaussianModel4D:
    """Remove the per-Gaussian time terms that the options switch off."""
    for name, on in (("dopacity", opts.time_opacity), ("dsh0", opts.time_color),
                     ("dshN", opts.time_specular)):
        if not on and name in model.splats:
            del model.splats[name]
    return model


def _params_finite(model: GaussianModel4D) -> bool:
    return all(bool(torch.isfinite(p).all()) for p in model.parameters())


def _options_key(opts: FitOptions) -> dict:
    d = dataclasses.asdict(opts)
    for k in _NON_RESULT_OPTIONS:
        d.pop(k, None)
    return d


# ------------------------------------------------------------------------------ evaluation


@torch.no_grad()
def evaluate_views(model: GaussianModel4D, views: list[TrainView], backend: str = "auto",
                   exposure: ExposureCorrection | None = None) -> pd.DataFrame:
    """PSNR / SSIM of every view rendered at its own time (images at the working size), with
    view ``i``'s colour correction ``exposure(., i)`` applied when given.

    With views of two times, also ``psnr_other_time``: the PSNR of the *other* time's render
    at the view's camera, its colours matched to the photo by one affine transform
    (:func:`affine_colour_match`, so that exposure and white balance do not count). Where
    the times share their Gaussians it is near ``psnr`` on every unchanged part of the view;
    where each time's photos took Gaussians of their own, the other time's render of the
    same surfaces is a guess and it falls far below (a real change lowers it too)."""
    rows = []
    times = sorted({v.time for v in views})
    cache = {t: model.at_time(t) for t in times}  # the Gaussians at each time, deformed once
    for i, v in enumerate(views):
        h, w = v.image.shape[:2]
        c, _, _ = rasterize_gaussians(cache[v.time], v.viewmat, v.K, w, h, None, "RGB", backend)
        pred = c[0] if exposure is None else exposure(c[0], i)
        pred = pred.clamp(0, 1)
        row = {"image": v.camera.image, "set": v.camera.set, "time": v.time,
               "psnr": float(psnr(pred, v.image)), "ssim": float(ssim(pred, v.image))}
        if len(times) == 2:
            other = times[1] if v.time == times[0] else times[0]
            c, _, _ = rasterize_gaussians(cache[other], v.viewmat, v.K, w, h, None, "RGB",
                                          backend)
            row["psnr_other_time"] = float(psnr(affine_colour_match(c[0], v.image), v.image))
        rows.append(row)
    columns = ["image", "set", "time", "psnr", "ssim"]
    return pd.DataFrame(rows, columns=columns + (["psnr_other_time"] if len(times) == 2 else []))


# ------------------------------------------------------------------------------ entry point


def _after_reset_hint(opts: FitOptions, it: int) -> str:
    """What to try when the fit failed at iteration ``it`` after an opacity reset in the fine
    phase without a hold of the deformation field ("" otherwise)."""
    last = opts.last_opacity_reset(it)
    if last is None or opts.reset_hold > 0 or last < opts.coarse_iters or not opts.deform:
        return ""  # no reset, already held, or no field learnt then
    return (f"; this followed the opacity reset at iteration {last}: set fit.reset_hold: 100 "
            "(the deformation field is held while the opacities recover) and re-run")


def fit_scene(scene_dir: str | Path, cameras_json: str | Path, points_ply: str | Path,
              out_dir: str | Path, options: FitOptions | None = None, device="auto",
              callback: Callable[[Trainer], None] | None = None) -> dict:
    """Fit the 4D model of a scene and write the ``fit/`` outputs (see module docstring).

    Args:
        scene_dir: the scene folder (image paths in cameras.json are relative to it).
        cameras_json: ``poses/cameras.json``; frames of sets before/after are trained on.
        points_ply: ``poses/points.ply`` (x y z red green blue).
        out_dir: ``results/<scene>/fit``.
        options: :class:`FitOptions` (defaults when None).
        device: "auto" | "cpu" | "cuda" | torch.device.
        callback: called with the trainer after every iteration (progress hooks, tests).
    Returns:
        summary dict: iterations, n_gaussians, seconds, psnr_t0/ssim_t0/psnr_t1/ssim_t1 (mean
        over training images), with both times psnr_other_time (its mean, see
        :func:`evaluate_views`), extent, resumed_from (iteration or 0), width, height.
    Raises:
        SceneError for unusable inputs; TrainingError when the loss becomes NaN/inf.
    """
    opts = options or FitOptions()
    dev = resolve_device(device)
    out = Path(out_dir)
    scene_dir = Path(scene_dir)
    cams = [c for c in load_cameras(cameras_json) if c.set in TRAIN_SETS]
    for s in TRAIN_SETS:
        if not any(c.set == s for c in cams):
            raise SceneError(f"{cameras_json}: no registered '{s}' images; the fit needs both "
                             "before and after images (check the poses stage)")
    xyz, rgb = read_points(points_ply)
    views = load_views(image_root(scene_dir, cameras_json), cams, opts.max_side, dev,
                       opts.coarse_downscale if opts.coarse_iters > 0 else 1)
    extent = camera_extent(np.stack([c.center for c in cams]))
    torch.manual_seed(opts.seed)
    model = GaussianModel4D.from_points(xyz, rgb, opts.sh_degree, opts.deform_config(),
                                        opts.init_opacity,
                                        opts.init_max_scale * extent,
                                        opts.reflection_height if opts.reflection else 0)
    model = _drop_time_terms(model, opts).to(dev)
    trainer = Trainer(model, views, opts, extent)
    log.info("fit: %d images (%d before, %d after) at %dx%d, %d initial Gaussians, extent %.3f",
             len(views), sum(c.set == "before" for c in cams), sum(c.set == "after" for c in cams),
             views[0].image.shape[1], views[0].image.shape[0], len(model), extent)

    ckpt = out / "ckpt" / "last.pt"
    fingerprint = _fingerprint(Path(cameras_json), Path(points_ply))
    key = _options_key(opts)
    resumed = 0
    remove_stale_temporaries(ckpt.parent)
    if ckpt.is_file():
        try:
            st = torch.load(ckpt, map_location="cpu", weights_only=True)
        except Exception as e:  # a checkpoint from a crash mid-write cannot exist (atomic)
            log.warning("ignoring unreadable checkpoint %s (%s)", ckpt, e)
            st = None
        if st and st.get("format") == CKPT_FORMAT and st.get("fingerprint") == fingerprint \
                and st.get("options") == key:
            trainer.load_state_dict(st)
            resumed = trainer.iteration
            log.info("resuming from %s at iteration %d", ckpt, resumed)
        elif st:
            log.warning("checkpoint %s is from other options or inputs; starting afresh", ckpt)

    def save_ckpt():
        if not _params_finite(trainer.model):
            raise FloatingPointError("parameters are not finite")
        st = trainer.state_dict()
        st["fingerprint"], st["options"] = fingerprint, key
        save_torch(st, ckpt)

    total = opts.total_iters
    bar = progress(total=total, initial=trainer.iteration, desc="fit")
    last_ckpt = resumed
    t_start = time.time() - trainer.elapsed
    try:
        while trainer.iteration < total:
            try:
                rec = trainer.step()
            except FloatingPointError as e:
                where = (f"the last good checkpoint is {ckpt} (iteration {last_ckpt}); lower the "
                         "learning rates in config 'fit' or delete the checkpoint to restart"
                         if last_ckpt else "no checkpoint was written yet")
                raise TrainingError(f"fit diverged at iteration {trainer.iteration + 1} ({e}); "
                                    f"{where}{_after_reset_hint(opts, trainer.iteration)}"
                                    ) from None
            trainer.elapsed = time.time() - t_start
            it = rec["iteration"]
            if rec["n_gaussians"] == 0:
                raise TrainingError(
                    f"fit collapsed at iteration {it}: the refine step pruned every Gaussian "
                    f"(opacity under prune_opacity = {opts.prune_opacity}, e.g. not yet "
                    "recovered from the opacity reset); the checkpoints replay the same run: "
                    "set another fit.seed, or fit.opacity_reset_every: 0, and re-run"
                    + _after_reset_hint(opts, it))
            if "densify" in rec:
                log.debug("iteration %d: densify %s", it, rec["densify"])
            if opts.log_every and (it % opts.log_every == 0 or it == total):
                row = {k: v for k, v in rec.items() if k != "densify"}
                row["seconds"] = round(trainer.elapsed, 2)
                trainer.rows.append(row)
                bar.set_postfix(loss=f"{rec['loss']:.4f}", psnr=f"{rec['psnr']:.1f}",
                                n=rec["n_gaussians"], phase=rec["phase"], refresh=False)
            bar.update(1)
            if opts.checkpoint_every and it % opts.checkpoint_every == 0 and it < total:
                try:
                    save_ckpt()
                except FloatingPointError as e:
                    raise TrainingError(f"fit diverged by iteration {it} ({e}); the last good "
                                        f"checkpoint is {ckpt} (iteration {last_ckpt})") from None
                last_ckpt = it
            if callback is not None:
                callback(trainer)
    finally:
        bar.close()
    model = trainer.model
    if not _params_finite(model):
        raise TrainingError(f"fit ended with non-finite parameters at iteration {total}; "
                            f"the last good checkpoint is {ckpt} (iteration {last_ckpt})")
    gate = trainer.time_gate()
    if gate is not None:
        model.apply_time_gate(gate)  # the saved model renders as trained, without the gate
        log.info("time terms kept for %d of %d Gaussians (in view in >= %d renders of each"
                 " time)", int(gate.sum()), len(gate), opts.time_min_views)
    model.eval()
    seconds = time.time() - t_start
    quality = evaluate_views(model, views, opts.backend, trainer.exposure)
    ref = cams[0]
    meta = {"camera": {k: getattr(ref, k) for k in ("width", "height", "fx", "fy", "cx", "cy")},
            "extent": extent, "iterations": trainer.iteration, "seconds": seconds,
            "working_size": [int(views[0].image.shape[1]), int(views[0].image.shape[0])],
            "options": dataclasses.asdict(opts)}
    save_model(model, out / "model.pt", meta)
    with torch.no_grad():
        for t in (0, 1):
            write_gaussians(out / f"gaussians_t{t}.ply", model.at_time(float(t)))
    write_csv(out / "train_log.csv", pd.DataFrame(trainer.rows))
    write_csv(out / "quality.csv", quality)
    if trainer.exposure is not None:
        table = trainer.exposure.table([v.camera.image for v in views])
        write_csv(out / "exposure.csv", table)
        log.info("colour correction per image: gain %.3f .. %.3f (1 = as the model)",
                 table["gain"].min(), table["gain"].max())
    if ckpt.is_file() and not opts.keep_checkpoint:
        ckpt.unlink()
    summary = {"iterations": trainer.iteration, "n_gaussians": len(model),
               "seconds": round(seconds, 2), "extent": extent, "resumed_from": resumed,
               "width": meta["working_size"][0], "height": meta["working_size"][1]}
    for t in (0, 1):
        q = quality[quality["time"] == t]
        summary[f"psnr_t{t}"] = float(q["psnr"].mean()) if len(q) else float("nan")
        summary[f"ssim_t{t}"] = float(q["ssim"].mean()) if len(q) else float("nan")
    if "psnr_other_time" in quality:
        summary["psnr_other_time"] = float(quality["psnr_other_time"].mean())
        log.info("the other time's render at the training photos (colours matched): PSNR %.2f dB "
                 "against %.2f dB at their own time (see fit/quality.csv: far below means each "
                 "time's photos took Gaussians of their own, and the two renders of a pose "
                 "differ where nothing changed)", summary["psnr_other_time"],
                 float(quality["psnr"].mean()))
    log.info("fit done: %s", summary)
    return summary


def fit_options_from_config(section: dict | None) -> FitOptions:
    """:class:`FitOptions` from the config section ``fit`` (unknown keys rejected)."""
    from ..options import from_config

    return from_config(FitOptions, section, "fit")


__all__ = ["FitOptions", "fit_scene", "Trainer", "TrainView", "load_views", "evaluate_views",
           "fit_options_from_config"]
