"""Deformation field of the 4D Gaussians: a HexPlane feature grid and a small MLP with heads
for Δposition, Δscale, Δrotation, Δopacity and ΔSH colour (after Wu et al., CVPR 2024).

HexPlane
--------
Six feature planes over the 4D coordinate (x, y, z, t): xy, xz, xt, yz, yt, zt (every pair of
axes 0..3, in that order). Positions are normalised to [-1, 1] over an axis-aligned box
(``aabb`` [2, 3], world units; points outside are clamped to the border) and time t in [0, 1]
maps to [-1, 1]. Each plane is sampled bilinearly (``grid_sample`` with corners aligned, so
t = 0 and t = 1 fall exactly on grid rows); features of the six planes are multiplied, and the
products of every resolution level are concatenated: output [N, features * levels].
Spatial planes start uniform in [0.5, 1.5] and time planes at 1 (so time has no effect before
training), as in K-Planes. On CPU the look-up runs in a compiled kernel
(:func:`gdiff.splat.csrc.hexplane_sample`, channels-last, several times faster than
``grid_sample``) when the positions need no gradient; ``grid_sample`` is the reference and
the fallback.

Heads are zero-initialised: the deformation is exactly zero until trained. Deltas are added
to the raw parameters (means, log-scales, wxyz quaternion, opacity logit, SH coefficients).
The positions enter the grid look-up as constants: the field is trained, the Gaussians move
through their own position gradient and the Δposition head, not through the slope of the
grid (that gradient is noisy on a piecewise-bilinear grid and costs a third of the look-up's
backward pass).
"""

from __future__ import annotations

import itertools
from dataclasses import asdict, dataclass, field

import torch
import torch.nn.functional as F
from torch import nn

from .losses import smoothness, tv

PLANES = tuple(itertools.combinations(range(4), 2))  # (0,1) xy ... (2,3) zt
SPATIAL = tuple(i for i, (a, b) in enumerate(PLANES) if b < 3)  # xy, xz, yz
TEMPORAL = tuple(i for i, (a, b) in enumerate(PLANES) if b == 3)  # xt, yt, zt


@dataclass
class DeformConfig:
    """Architecture of the deformation field (saved with the model to rebuild it)."""

    resolution: list[int] = field(default_factory=lambda: [48, 48, 48])  # coarsest x, y, z
    time_resolution: int = 2  # samples along t (2: linear in t between before and after)
    multires: list[int] = field(default_factory=lambda: [1, 2])  # spatial resolution multipliers
    features: int = 16  # channels per plane
    width: int = 32  # MLP width
    depth: int = 2  # linear layers of the shared trunk
    head_layers: int = 0  # hidden layers in each head (4DGS uses 1; 0 is ~10x cheaper)
    position: bool = True
    scale: bool = True
    rotation: bool = True
    opacity: bool = True
    color: bool = True
    color_degree: int = 0  # SH degree the colour head changes (0: view-independent colour)
    sh_coeffs: int = 16  # K coefficients per channel stored by the model (set by the model)

    def to_dict(self) -> dict:
        return asdict(self)


class HexPlane(nn.Module):
    """Multi-resolution HexPlane feature grid (see module docstring).

    forward(xyz [N, 3] world units, t float or [N] tensor in [0, 1]) -> [N, features * levels].
    """

    def __init__(self, resolution=(48, 48, 48), time_resolution: int = 2,
                 multires=(1, 2), features: int = 16):
        super().__init__()
        self.features = int(features)
        self.levels = len(multires)
        self.grids = nn.ParameterList()
        for m in multires:
            res = [int(r * m) for r in resolution] + [int(time_resolution)]
            for a, b in PLANES:
                # grid_sample: width indexes the first coordinate (a), height the second (b)
                shape = (1, self.features, res[b], res[a])
                if b == 3:
                    p = torch.ones(shape)
                else:
                    p = torch.empty(shape).uniform_(0.5, 1.5)
                self.grids.append(nn.Parameter(p))
        self.register_buffer("aabb", torch.tensor([[-1.0] * 3, [1.0] * 3]))

    @property
    def out_dim(self) -> int:
        return self.features * self.levels

    def set_aabb(self, lo, hi) -> None:
        """Set the box [lo, hi] (world units, [3] each) mapped onto the grid."""
        with torch.no_grad():
            self.aabb.copy_(torch.stack([torch.as_tensor(lo), torch.as_tensor(hi)]).to(self.aabb))

    def normalize(self, xyz: torch.Tensor, t) -> torch.Tensor:
        """[N, 4] coordinates in [-1, 1] (x, y, z clamped to the box)."""
        lo, hi = self.aabb[0], self.aabb[1]
        p = ((xyz - lo) / (hi - lo).clamp_min(1e-9)) * 2.0 - 1.0
        p = p.clamp(-1.0, 1.0)
        if not torch.is_tensor(t):
            t = torch.full_like(p[:, :1], float(t))
        else:
            t = t.to(p).reshape(-1, 1).expand(p.shape[0], 1)
        return torch.cat([p, t * 2.0 - 1.0], dim=1)

    def forward(self, xyz: torch.Tensor, t) -> torch.Tensor:
        coords = self.normalize(xyz, t)
        if not coords.requires_grad and _fused_kernel(coords) is not None:
            return self._forward_fused(coords)
        n = coords.shape[0]
        outs = []
        for level in range(self.levels):
            feat = None
            for j, (a, b) in enumerate(PLANES):
                grid = self.grids[level * len(PLANES) + j]
                uv = coords[:, (a, b)].view(1, n, 1, 2)
                f = F.grid_sample(grid, uv, mode="bilinear", padding_mode="border",
                                  align_corners=True)  # [1, F, N, 1]
                f = f.view(self.features, n)
                feat = f if feat is None else feat * f
            outs.append(feat.t())
        return torch.cat(outs, dim=1)

    def _forward_fused(self, coords: torch.Tensor) -> torch.Tensor:
        """The same features through the compiled channels-last look-up (CPU, float32)."""
        from .csrc import hexplane_sample

        rows, meta = [], []
        offset = 0
        for k, grid in enumerate(self.grids):
            a, b = PLANES[k % len(PLANES)]
            f, h, w = grid.shape[1:]
            rows.append(grid.reshape(f, h * w).t())
            meta.append((a, b, w, h, offset))
            offset += h * w
        table = torch.cat(rows)  # [R, F]
        planes = torch.tensor(meta, dtype=torch.long)
        out = hexplane_sample(table, coords, planes, len(PLANES))  # [N, levels, F]
        return out.reshape(coords.shape[0], -1)

    def _planes(self, which):
        return [self.grids[level * len(PLANES) + j] for level in range(self.levels)
                for j in which]

    def plane_tv(self) -> torch.Tensor:
        """Total variation of the spatial planes (mean over planes)."""
        ps = self._planes(SPATIAL)
        return sum(tv(p) for p in ps) / len(ps)

    def time_smoothness(self) -> torch.Tensor:
        """Second-difference smoothness along t of the time planes (0 if t has < 3 samples)."""
        ps = self._planes(TEMPORAL)
        return sum(smoothness(p, dim=2) for p in ps) / len(ps)

    def time_l1(self) -> torch.Tensor:
        """Mean |1 - value| of the time planes: pulls the field towards no change over time."""
        ps = self._planes(TEMPORAL)
        return sum((1.0 - p).abs().mean() for p in ps) / len(ps)


def _fused_kernel(coords: torch.Tensor):
    """The compiled look-up when it applies (float32 CPU tensors, kernel built), else None."""
    if coords.device.type != "cpu" or coords.dtype != torch.float32:
        return None
    try:
        from . import csrc
    except ImportError:
        return None
    return csrc.load(required=False)


def _head(width: int, out: int, hidden: int) -> nn.Sequential:
    layers: list[nn.Module] = [nn.ReLU()]
    for _ in range(hidden):
        layers += [nn.Linear(width, width), nn.ReLU()]
    head = nn.Sequential(*layers, nn.Linear(width, out))
    nn.init.zeros_(head[-1].weight)
    nn.init.zeros_(head[-1].bias)
    return head


class Deformation(nn.Module):
    """HexPlane + MLP deformation (see module docstring).

    forward(means [N, 3], t) -> dict of deltas for the enabled heads: ``means`` [N, 3],
    ``scales`` [N, 3] (log space), ``quats`` [N, 4], ``opacities`` [N] (logit space),
    ``sh`` [N, Kc, 3] for the first Kc = (color_degree+1)^2 SH coefficients.
    """

    def __init__(self, cfg: DeformConfig):
        super().__init__()
        self.cfg = cfg
        self.color_coeffs = min((cfg.color_degree + 1) ** 2, cfg.sh_coeffs)
        self.field = HexPlane(cfg.resolution, cfg.time_resolution, cfg.multires, cfg.features)
        layers: list[nn.Module] = [nn.Linear(self.field.out_dim, cfg.width)]
        for _ in range(cfg.depth - 1):
            layers += [nn.ReLU(), nn.Linear(cfg.width, cfg.width)]
        self.trunk = nn.Sequential(*layers)
        outs = {"means": 3 if cfg.position else 0, "scales": 3 if cfg.scale else 0,
                "quats": 4 if cfg.rotation else 0, "opacities": 1 if cfg.opacity else 0,
                "sh": 3 * self.color_coeffs if cfg.color else 0}
        self.heads = nn.ModuleDict({k: _head(cfg.width, d, cfg.head_layers)
                                    for k, d in outs.items() if d})

    def forward(self, means: torch.Tensor, t) -> dict[str, torch.Tensor]:
        h = self.trunk(self.field(means.detach(), t))
        if self.cfg.head_layers == 0:
            # every head is ReLU + Linear on the same input: one ReLU and one matrix product
            # for all of them (the same values as head by head, a third of the work)
            lin = [head[-1] for head in self.heads.values()]
            both = F.linear(F.relu(h), torch.cat([m.weight for m in lin]),
                            torch.cat([m.bias for m in lin]))
            outs = both.split([m.out_features for m in lin], dim=1)
        else:
            outs = [head(h) for head in self.heads.values()]
        out = {}
        for name, d in zip(self.heads.keys(), outs):
            if name == "opacities":
                d = d[:, 0]
            elif name == "sh":
                d = d.reshape(-1, self.color_coeffs, 3)
            out[name] = d
        return out

    def regularizers(self) -> dict[str, torch.Tensor]:
        """Grid regularisers: ``plane_tv``, ``time_smooth``, ``time_l1`` (scalars)."""
        return {"plane_tv": self.field.plane_tv(), "time_smooth": self.field.time_smoothness(),
                "time_l1": self.field.time_l1()}

    def grid_parameters(self):
        return list(self.field.parameters())

    def mlp_parameters(self):
        return list(self.trunk.parameters()) + list(self.heads.parameters())
