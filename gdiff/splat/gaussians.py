"""3D Gaussians: the activated parameter set, initialisation from SfM points, adaptive density
control (clone / split / prune / opacity reset) on tensors.

Conventions
-----------
Raw (optimised) per-Gaussian parameters live in an ``nn.ParameterDict`` with the names

====================  =================  =========================================
name                  shape              meaning
====================  =================  =========================================
``means``             [N, 3]             centre, world units (metres in the scenes)
``scales``            [N, 3]             log of the standard deviations along the axes
``quats``             [N, 4]             rotation quaternion, wxyz, not normalised
``opacities``         [N]                logit of opacity (at t = 0.5)
``dopacity``          [N]                change of that logit over time: at time t the logit
                                         is ``opacities + (2t - 1) dopacity`` (4D models)
``sh0``               [N, 1, 3]          degree-0 SH coefficient per colour channel
``dsh0``              [N, 1, 3]          its change over time: ``sh0 + (2t - 1) dsh0``
``shN``               [N, K-1, 3]        higher-order SH coefficients, K = (degree+1)^2
``dshN``              [N, K-1, 3]        their change over time: ``shN + (2t - 1) dshN``
                                         (view-dependent light: highlights that move
                                         with the lighting)
====================  =================  =========================================

Colours are fitted to sRGB-encoded image values; rendered colour = SH(view dir) + 0.5 (3DGS).
Any other entry of the dict whose first dimension is N (e.g. a per-Gaussian encoding added by
a later stage) is carried along by every densification operation.

Densification works with a ``torch.optim.Optimizer`` whose parameter groups each hold exactly
one of those parameters and carry its name under ``"name"``; Adam moments are edited together
with the parameters (new Gaussians start with zero moments).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
import torch
from torch import nn

SH_C0 = 0.28209479177387814  # Y_0^0 = 1 / (2 sqrt(pi))

PARAM_NAMES = ("means", "scales", "quats", "opacities", "dopacity", "sh0", "dsh0", "shN", "dshN")
TIME_TERMS = ("dopacity", "dsh0", "dshN")  # per-Gaussian changes over time (see above)


def rgb_to_sh0(rgb: torch.Tensor) -> torch.Tensor:
    """Colour in [0, 1] -> degree-0 SH coefficient (rendered colour = SH_C0 * c + 0.5)."""
    return (rgb - 0.5) / SH_C0


def sh0_to_rgb(sh0: torch.Tensor) -> torch.Tensor:
    """Degree-0 SH coefficient -> view-independent colour (not clamped)."""
    return sh0 * SH_C0 + 0.5


def num_sh_coeffs(degree: int) -> int:
    """K = (degree + 1)^2 coefficients per channel for SH up to ``degree``."""
    return (degree + 1) ** 2


@dataclass
class Gaussians:
    """Activated Gaussians ready for rasterisation (all tensors share device and N).

    means [N, 3] world units; quats [N, 4] unit wxyz; scales [N, 3] standard deviations (world
    units, > 0); opacities [N] in (0, 1); sh [N, K, 3] SH coefficients (K = (max degree+1)^2);
    ``sh_degree`` is the degree to evaluate (coefficients beyond it are ignored). Optional
    mirror-direction specular term (:mod:`gdiff.splat.reflection`): ``reflectivity`` [N]
    strength in (0, 1) and ``environment``, a callable mapping world directions [..., 3] to
    radiance [..., 3] at this time; both set or both None (plain SH colour).
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    sh: torch.Tensor
    sh_degree: int
    reflectivity: torch.Tensor | None = None
    environment: Callable[[torch.Tensor], torch.Tensor] | None = None

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def detach(self) -> "Gaussians":
        """The per-Gaussian tensors detached (``environment`` is kept as it is)."""
        r = self.reflectivity
        return replace(self, means=self.means.detach(), quats=self.quats.detach(),
                       scales=self.scales.detach(), opacities=self.opacities.detach(),
                       sh=self.sh.detach(), reflectivity=None if r is None else r.detach())

    def subset(self, index: torch.Tensor) -> "Gaussians":
        """The Gaussians selected by a bool mask or index tensor over N."""
        r = self.reflectivity
        return replace(self, means=self.means[index], quats=self.quats[index],
                       scales=self.scales[index], opacities=self.opacities[index],
                       sh=self.sh[index], reflectivity=None if r is None else r[index])


# --------------------------------------------------------------------------------------------
# initialisation


def knn_scales(xyz: np.ndarray, k: int = 3) -> np.ndarray:
    """Per-point isotropic scale: RMS distance to the ``k`` nearest other points, [P].

    Uses a KD-tree (scipy); coincident points get the smallest positive distance in the cloud.
    """
    from scipy.spatial import cKDTree

    xyz = np.asarray(xyz, dtype=np.float64)
    if len(xyz) < 2:
        return np.full(len(xyz), 0.01)
    k = min(k, len(xyz) - 1)
    d, _ = cKDTree(xyz).query(xyz, k=k + 1)
    d = np.sqrt(np.mean(d[:, 1:] ** 2, axis=1))
    positive = d[d > 0]
    floor = positive.min() if positive.size else 1e-3
    return np.maximum(d, floor)


def init_params(xyz: np.ndarray, rgb: np.ndarray, sh_degree: int = 3,
                init_opacity: float = 0.1, knn: int = 3,
                max_scale: float | None = None) -> dict[str, torch.Tensor]:
    """Raw parameters (see module docstring) for Gaussians at SfM points.

    xyz [P, 3] world positions; rgb [P, 3] colours in [0, 1] (sRGB-encoded). Scales are
    isotropic, from nearest-neighbour distances, at most ``max_scale`` (world units; isolated
    far points otherwise start as Gaussians metres wide that cover every image and make the
    first iterations very slow); rotations identity; SH beyond degree 0 zero.
    Returns float32 CPU tensors.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    rgb = np.clip(np.asarray(rgb, dtype=np.float64), 0.0, 1.0)
    n = len(xyz)
    s = knn_scales(xyz, knn)
    if max_scale is not None:
        s = np.minimum(s, max_scale)
    quats = np.zeros((n, 4))
    quats[:, 0] = 1.0
    k = num_sh_coeffs(sh_degree)
    t = lambda a: torch.tensor(a, dtype=torch.float32)  # noqa: E731
    return {
        "means": t(xyz),
        "scales": t(np.log(s))[:, None].repeat(1, 3),
        "quats": t(quats),
        "opacities": torch.full((n,), math.log(init_opacity / (1 - init_opacity))),
        "dopacity": torch.zeros(n),
        "sh0": rgb_to_sh0(t(rgb))[:, None, :],
        "dsh0": torch.zeros(n, 1, 3),
        "shN": torch.zeros(n, k - 1, 3),
        "dshN": torch.zeros(n, k - 1, 3),
    }


def camera_extent(centers: np.ndarray) -> float:
    """Scene extent as in 3DGS: 1.1 x the largest distance of a camera centre from their mean.

    centers [C, 3]. Density-control thresholds and the position learning rate scale with it.
    """
    centers = np.asarray(centers, dtype=np.float64)
    d = np.linalg.norm(centers - centers.mean(axis=0), axis=1)
    return float(1.1 * max(d.max(), 1e-6))


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Unit or non-unit quaternions wxyz [N, 4] -> rotation matrices [N, 3, 3]."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(q.shape[:-1] + (3, 3))


# --------------------------------------------------------------------------------------------
# editing parameters together with their optimiser state


def _group_of(optimizer: torch.optim.Optimizer, name: str):
    for g in optimizer.param_groups:
        if g.get("name") == name:
            return g
    return None


def edit_params(params: nn.ParameterDict, optimizer: torch.optim.Optimizer | None,
                param_fn: Callable[[str, torch.Tensor], torch.Tensor],
                state_fn: Callable[[str, torch.Tensor], torch.Tensor]) -> None:
    """Replace every per-Gaussian parameter ``p`` by ``param_fn(name, p)`` (a new leaf) and every
    tensor in its optimiser state with the same first dimension by ``state_fn(key, v)``.

    Optimiser groups are matched by their ``"name"``; parameters without a group (e.g. frozen
    ones) are edited too.
    """
    for name in list(params.keys()):
        old = params[name]
        new = nn.Parameter(param_fn(name, old.detach()), requires_grad=old.requires_grad)
        group = _group_of(optimizer, name) if optimizer is not None else None
        if group is not None:
            state = optimizer.state.pop(old, None)
            if state is not None:
                for key, v in list(state.items()):
                    if isinstance(v, torch.Tensor) and v.dim() > 0 and v.shape[0] == old.shape[0]:
                        state[key] = state_fn(key, v)
                optimizer.state[new] = state
            group["params"] = [new]
        params[name] = new


def append_gaussians(params: nn.ParameterDict, optimizer: torch.optim.Optimizer | None,
                     new: dict[str, torch.Tensor]) -> None:
    """Append Gaussians with the given raw values (every key of ``params`` must be in ``new``);
    their optimiser moments start at zero."""
    missing = set(params.keys()) - set(new)
    if missing:
        raise KeyError(f"append_gaussians: values missing for {sorted(missing)}")
    m = next(iter(new.values())).shape[0]
    edit_params(params, optimizer,
                lambda n, p: torch.cat([p, new[n].to(p)]),
                lambda k, v: torch.cat([v, v.new_zeros((m,) + v.shape[1:])]))


def keep_gaussians(params: nn.ParameterDict, optimizer: torch.optim.Optimizer | None,
                   keep: torch.Tensor) -> None:
    """Keep only the Gaussians where the bool mask ``keep`` [N] is true."""
    edit_params(params, optimizer, lambda n, p: p[keep], lambda k, v: v[keep])


def duplicate(params: nn.ParameterDict, optimizer: torch.optim.Optimizer | None,
              mask: torch.Tensor) -> None:
    """Clone the Gaussians selected by ``mask`` [N] (copies appended at the end)."""
    append_gaussians(params, optimizer, {k: p.detach()[mask] for k, p in params.items()})


def split(params: nn.ParameterDict, optimizer: torch.optim.Optimizer | None, mask: torch.Tensor,
          n: int = 2, shrink: float = 1.6) -> None:
    """Replace each selected Gaussian by ``n`` children sampled from it (3DGS split).

    Children are placed at samples of the parent's Gaussian, with scales divided by ``shrink``;
    other attributes are copied. Uses torch's global RNG (saved in checkpoints).
    """
    sel = {k: p.detach()[mask] for k, p in params.items()}
    m = sel["means"].shape[0]
    if m == 0:
        return
    s = sel["scales"].exp()
    rot = quat_to_rotmat(sel["quats"])
    z = torch.randn(n, m, 3, device=s.device, dtype=s.dtype) * s[None]
    offsets = torch.einsum("mij,nmj->nmi", rot, z)
    children = {k: v.repeat((n,) + (1,) * (v.dim() - 1)) for k, v in sel.items()}
    children["means"] = (sel["means"][None] + offsets).reshape(n * m, 3)
    children["scales"] = (sel["scales"] - math.log(shrink)).repeat(n, 1)
    keep_gaussians(params, optimizer, ~mask)
    append_gaussians(params, optimizer, children)


def reset_opacity(params: nn.ParameterDict, optimizer: torch.optim.Optimizer | None,
                  value: float = 0.01) -> None:
    """Clamp every opacity to at most ``value`` and zero the opacity's optimiser moments.

    With a ``dopacity`` entry the cap holds at every time t in [0, 1]: the logit at the time
    where it is largest (``opacities + |dopacity|``) is brought down to the cap.
    """
    cap = math.log(value / (1 - value))
    old = params["opacities"]
    raw = old.detach()
    if "dopacity" in params:
        top = raw + params["dopacity"].detach().abs()
        raw = raw - (top - cap).clamp_min(0.0)
    new = nn.Parameter(raw.clamp_max(cap), requires_grad=old.requires_grad)
    group = _group_of(optimizer, "opacities") if optimizer is not None else None
    if group is not None:
        state = optimizer.state.pop(old, None)
        if state is not None:
            for key, v in list(state.items()):
                if isinstance(v, torch.Tensor) and v.shape == old.shape:
                    state[key] = torch.zeros_like(v)
            optimizer.state[new] = state
        group["params"] = [new]
    params["opacities"] = new


# --------------------------------------------------------------------------------------------
# adaptive density control


class DensifyStats:
    """Per-Gaussian statistics of the rendered views.

    Between two refinements: ``grad2d`` [N], sum of |d loss / d mean2d| in NDC units (pixels x
    size/2), ``count`` [N], how many rendered views saw the Gaussian, ``max_radius`` [N],
    largest screen radius seen, as a fraction of max(width, height).

    Over the whole fit: ``seen`` [N, T], in how many rendered training views of each of the T
    times the Gaussian was in view (not culled, centre inside the image, whatever its opacity;
    see :meth:`observe`): renders, so a photo rendered in k epochs counts k times. A clone or
    split child inherits its parent's row; refinements keep it.
    """

    def __init__(self, n: int, device: torch.device | str | None = None, n_times: int = 2):
        self.grad2d = torch.zeros(n, device=device)
        self.count = torch.zeros(n, device=device)
        self.max_radius = torch.zeros(n, device=device)
        self.seen = torch.zeros(n, n_times, device=device)

    def __len__(self) -> int:
        return int(self.grad2d.shape[0])

    @torch.no_grad()
    def observe(self, radii: torch.Tensor, time_index: int, means2d: torch.Tensor | None = None,
                width: int = 0, height: int = 0) -> None:
        """Count the rendered views of time ``time_index`` that see each Gaussian (every call
        adds; the same photo rendered again counts again): radii [C, N] or
        [C, N, 2] (pixels, 0 = culled: behind the camera or off the image). With ``means2d``
        [C, N, 2] (pixels) and the image size, only a Gaussian whose centre falls inside the
        image counts (one that only reaches in with its border tells little about itself)."""
        if radii.dim() == 3:
            radii = radii.max(dim=-1).values
        vis = radii > 0
        if means2d is not None:
            m = means2d.detach()
            vis = vis & (m[..., 0] >= 0) & (m[..., 0] < width) & (m[..., 1] >= 0) \
                & (m[..., 1] < height)
        self.seen[:, time_index] += vis.sum(0).to(self.seen.dtype)

    def seen_at_all_times(self, min_views: int) -> torch.Tensor:
        """[N] bool: seen in at least ``min_views`` rendered views of every time."""
        return (self.seen >= min_views).all(dim=1)

    @torch.no_grad()
    def update(self, means2d_grad: torch.Tensor, radii: torch.Tensor, width: int,
               height: int, present: torch.Tensor | None = None) -> None:
        """Accumulate one rasterised batch: means2d_grad [C, N, 2] (pixels), radii [C, N] or
        [C, N, 2] (pixels; 0 = not visible).

        ``present`` [C, N] or [N] (bool) marks the Gaussians that exist in this view (e.g.
        opacity at the view's time above the prune level); the others are not counted, so a
        Gaussian of an object seen at one time only is judged on the views of that time.
        """
        if radii.dim() == 3:
            radii = radii.max(dim=-1).values
        c = means2d_grad.shape[0]
        g = means2d_grad.clone()
        g[..., 0] *= width / 2.0 * c
        g[..., 1] *= height / 2.0 * c
        vis = radii > 0
        if present is not None:
            vis = vis & present.to(vis.device).expand_as(vis)
        norm = g.norm(dim=-1) * vis
        self.grad2d += norm.sum(0)
        self.count += vis.sum(0).to(self.count.dtype)
        r = (radii.to(self.max_radius.dtype) / float(max(width, height))).max(0).values
        torch.maximum(self.max_radius, r, out=self.max_radius)

    def keep(self, mask: torch.Tensor) -> None:
        self.grad2d, self.count, self.max_radius, self.seen = (
            self.grad2d[mask], self.count[mask], self.max_radius[mask], self.seen[mask])

    def append(self, m: int, seen: torch.Tensor | None = None) -> None:
        """Append ``m`` Gaussians with zero window statistics and ``seen`` [m, T] (the
        parents' rows; zeros when None)."""
        z = self.grad2d.new_zeros(m)
        self.grad2d = torch.cat([self.grad2d, z])
        self.count = torch.cat([self.count, z])
        self.max_radius = torch.cat([self.max_radius, z])
        if seen is None:
            seen = self.seen.new_zeros(m, self.seen.shape[1])
        self.seen = torch.cat([self.seen, seen.to(self.seen)])

    def reset(self) -> None:
        """Clear the window statistics (``seen`` is kept)."""
        self.grad2d.zero_()
        self.count.zero_()
        self.max_radius.zero_()

    def state_dict(self) -> dict:
        return {"grad2d": self.grad2d, "count": self.count, "max_radius": self.max_radius,
                "seen": self.seen}

    def load_state_dict(self, d: dict) -> None:
        self.grad2d, self.count, self.max_radius = d["grad2d"], d["count"], d["max_radius"]
        # checkpoints without view counts: every Gaussian counts as seen at every time
        self.seen = d.get("seen", torch.full((len(self.grad2d), self.seen.shape[1]), 1e9,
                                             device=self.grad2d.device))


@dataclass
class DensifyThresholds:
    """3DGS density-control thresholds (3D sizes are fractions of the scene extent)."""

    grow_grad2d: float = 0.0002  # mean NDC-space gradient norm above which a Gaussian grows
    grow_scale3d: float = 0.01  # <= this x extent: clone; above: split
    prune_opacity: float = 0.005  # prune when the (largest over time) opacity is below
    prune_scale3d: float = 0.1  # prune when the largest axis exceeds this x extent
    prune_scale2d: float = 0.15  # prune when the screen radius exceeds this x image size
    max_gaussians: int = 0  # 0 = no cap; else growth picks the highest gradients up to the cap


@torch.no_grad()
def refine(params: nn.ParameterDict, optimizer: torch.optim.Optimizer | None,
           stats: DensifyStats, th: DensifyThresholds, extent: float,
           effective: Callable[[], tuple[torch.Tensor, torch.Tensor]] | None = None,
           prune_large: bool = True) -> dict[str, int]:
    """One 3DGS refinement: clone small / split large Gaussians with a high mean view-space
    gradient, then prune transparent ones (and, when ``prune_large``, huge ones).

    ``effective()`` returns (opacity [N], max scale [N]) used for pruning, evaluated after
    growth; a 4D model passes the largest values over the times it is trained on, so a
    Gaussian visible at any time is kept. Default: from the raw parameters.
    Resets the window statistics of ``stats`` (``seen`` follows the Gaussians). Returns counts
    {"cloned", "split", "pruned", "n"}.
    """
    n0 = len(params["means"])
    grads = stats.grad2d / stats.count.clamp_min(1)
    high = (grads > th.grow_grad2d) & (stats.count > 0)
    if th.max_gaussians > 0:
        room = max(th.max_gaussians - n0, 0)
        if int(high.sum()) > room:
            # every candidate adds one Gaussian (a split replaces 1 by 2)
            top = torch.topk(torch.where(high, grads, torch.full_like(grads, -1.0)), room).indices
            high = torch.zeros_like(high)
            high[top] = True
    small = params["scales"].exp().max(dim=-1).values <= th.grow_scale3d * extent
    clone_mask = high & small
    split_mask = high & ~small
    n_clone, n_split = int(clone_mask.sum()), int(split_mask.sum())
    if n_clone:
        duplicate(params, optimizer, clone_mask)
        stats.append(n_clone, stats.seen[clone_mask])
        split_mask = torch.cat([split_mask, split_mask.new_zeros(n_clone)])
    if n_split:
        children_seen = stats.seen[split_mask].repeat(2, 1)  # split() appends 2 x the parents
        split(params, optimizer, split_mask)
        stats.keep(~split_mask)
        stats.append(2 * n_split, children_seen)
    if effective is None:
        opa = torch.sigmoid(params["opacities"])
        size = params["scales"].exp().max(dim=-1).values
    else:
        opa, size = effective()
    prune = opa < th.prune_opacity
    if prune_large:
        prune |= size > th.prune_scale3d * extent
        prune |= stats.max_radius > th.prune_scale2d
    n_prune = int(prune.sum())
    if n_prune:
        keep_gaussians(params, optimizer, ~prune)
        stats.seen = stats.seen[~prune]
    stats.grad2d = torch.zeros(len(params["means"]), device=stats.grad2d.device)
    stats.count = torch.zeros_like(stats.grad2d)
    stats.max_radius = torch.zeros_like(stats.grad2d)
    return {"cloned": n_clone, "split": n_split, "pruned": n_prune, "n": len(params["means"])}
