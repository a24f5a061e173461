"""The 4D Gaussian model: static 3D Gaussians + a deformation field over time t in [0, 1].

API used by later stages::

    from gdiff.splat.model import load_model
    model = load_model("results/<scene>/fit/model.pt", device)   # GaussianModel4D (eval mode)
    g = model.at_time(0.0)   # Gaussians: means [N,3], quats [N,4] wxyz, scales [N,3],
                             # opacities [N], sh [N,K,3], sh_degree  (differentiable)

``model.splats`` is an ``nn.ParameterDict`` of raw per-Gaussian parameters (names and shapes in
:mod:`gdiff.splat.gaussians`); among them ``dopacity`` [N], the per-Gaussian change of the
opacity logit over time: ``logit(t) = opacities + (2t - 1) dopacity (+ the field's delta)``, so
a Gaussian can exist at one time only (an added or removed object) from the first iteration
on, without waiting for the deformation field; likewise ``dsh0`` [N, 1, 3] changes the
diffuse colour, ``sh0 + (2t - 1) dsh0`` (off by default, the fit's ``time_color``: it can
draw an added object at the other time too, recoloured) and ``dshN`` [N, K-1, 3] the
view-dependent SH, ``shN + (2t - 1) dshN`` (highlights on glossy surfaces move with the
light). With ``reflection_height`` > 0, ``reflectivity`` [N] (logit of a strength) and
``model.environment`` add a highlight looked up in the mirror direction
(:mod:`gdiff.splat.reflection`). Any of them may be absent (the fit's ``time_opacity`` /
``time_color`` / ``time_specular``; files from before ``dshN`` load with no view-dependent
change). While fitting, ``time_gate`` [N] (see :meth:`raw_at_time`)
switches these terms off for Gaussians not yet observed at both times; the saved model has
the gate folded in (:meth:`apply_time_gate`). A later stage may add its own per-Gaussian
entries (first dimension N), which densification carries along and
:func:`save_model`/:func:`load_model` preserve. ``model.deformation`` is a
:class:`~gdiff.splat.deform.Deformation` (or None for a static model); its deltas are applied
only once ``model.deform_on`` is set (the fine phase).

``model.pt`` holds ``{"format", "version", "config", "state_dict", "meta"}``: ``config``
(SH degree, deformation architecture) + ``state_dict`` rebuild the module; ``meta`` holds
facts about the fit (training intrinsics, scene extent, ...).
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..errors import ModelFileError
from ..io import save_torch
from .deform import DeformConfig, Deformation
from .gaussians import TIME_TERMS, Gaussians, init_params, num_sh_coeffs
from .reflection import Environment

INIT_REFLECTIVITY_LOGIT = -2.0  # strength sigmoid(-2) ~ 0.12 before it is learnt

FORMAT = "gdiff.GaussianModel4D"
VERSION = 1


class GaussianModel4D(nn.Module):
    """3D Gaussians deformed over time (see module docstring).

    Args:
        n: number of Gaussians (parameters start at neutral values; see :meth:`from_points`).
        sh_degree: largest SH degree stored (K = (sh_degree+1)^2 coefficients).
        deform: deformation architecture, or None for a static model.
        reflection_height: rows of the environment maps of the mirror-direction specular term
            (:mod:`gdiff.splat.reflection`; adds ``splats["reflectivity"]`` [N] and
            ``model.environment``), 0 for none.
    """

    def __init__(self, n: int = 0, sh_degree: int = 3,
                 deform: DeformConfig | dict | None = None, reflection_height: int = 0):
        super().__init__()
        self.sh_degree = int(sh_degree)
        k = num_sh_coeffs(self.sh_degree)
        quats = torch.zeros(n, 4)
        quats[:, 0] = 1.0
        self.splats = nn.ParameterDict({
            "means": nn.Parameter(torch.zeros(n, 3)),
            "scales": nn.Parameter(torch.full((n, 3), -4.0)),
            "quats": nn.Parameter(quats),
            "opacities": nn.Parameter(torch.zeros(n)),
            "dopacity": nn.Parameter(torch.zeros(n)),
            "sh0": nn.Parameter(torch.zeros(n, 1, 3)),
            "dsh0": nn.Parameter(torch.zeros(n, 1, 3)),
            "shN": nn.Parameter(torch.zeros(n, k - 1, 3)),
            "dshN": nn.Parameter(torch.zeros(n, k - 1, 3)),
        })
        if isinstance(deform, dict):
            deform = DeformConfig(**deform)
        if deform is not None:
            deform.sh_coeffs = k
            self.deformation: Deformation | None = Deformation(deform)
        else:
            self.deformation = None
        self.environment: Environment | None = None
        if reflection_height > 0:
            self.splats["reflectivity"] = nn.Parameter(torch.full((n,), INIT_REFLECTIVITY_LOGIT))
            self.environment = Environment(reflection_height)
        self.register_buffer("active_sh_degree", torch.tensor(0, dtype=torch.long))
        self.register_buffer("deform_on", torch.tensor(False))

    # ---------------------------------------------------------------- construction / config
    @classmethod
    def from_points(cls, xyz: np.ndarray, rgb: np.ndarray, sh_degree: int = 3,
                    deform: DeformConfig | None = None, init_opacity: float = 0.1,
                    max_scale: float | None = None,
                    reflection_height: int = 0) -> "GaussianModel4D":
        """Gaussians at SfM points xyz [P, 3] with colours rgb [P, 3] in [0, 1]; initial
        scales at most ``max_scale`` (world units, see :func:`init_params`)."""
        params = init_params(xyz, rgb, sh_degree, init_opacity, max_scale=max_scale)
        model = cls(len(xyz), sh_degree, deform, reflection_height)
        with torch.no_grad():
            for k, v in params.items():
                model.splats[k].copy_(v)
        return model

    def config(self) -> dict:
        """Small dict that, with :meth:`state_dict`, rebuilds the module."""
        return {"sh_degree": self.sh_degree,
                "deform": self.deformation.cfg.to_dict() if self.deformation else None,
                "reflection_height": self.environment.height if self.environment else 0}

    @classmethod
    def from_state(cls, config: dict, state_dict: dict) -> "GaussianModel4D":
        """Rebuild from :meth:`config` and a state dict (any N, extra ``splats.*`` entries)."""
        n = int(state_dict["splats.means"].shape[0])
        model = cls(n, config["sh_degree"], config.get("deform"),
                    config.get("reflection_height", 0))
        state_dict = dict(state_dict)
        ref = state_dict["splats.means"]
        # models from before the time-opacity term: no change of opacity over time
        state_dict.setdefault("splats.dopacity", ref.new_zeros(n))
        state_dict.setdefault("splats.dsh0", ref.new_zeros(n, 1, 3))
        state_dict.setdefault("splats.dshN", torch.zeros_like(state_dict["splats.shN"]))
        for key, v in state_dict.items():
            if key.startswith("splats."):
                name = key.split(".", 1)[1]
                model.splats[name] = nn.Parameter(torch.empty_like(v))
        model.load_state_dict(state_dict)
        return model

    def __len__(self) -> int:
        return int(self.splats["means"].shape[0])

    @property
    def device(self) -> torch.device:
        return self.splats["means"].device

    @property
    def deforming(self) -> bool:
        return self.deformation is not None and bool(self.deform_on)

    # ---------------------------------------------------------------- evaluation
    def raw_at_time(self, t, time_gate: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Raw (unactivated) parameters at time t (float or 0-d tensor in [0, 1]):
        means, scales (log), quats (unnormalised), opacities (logit), sh [N, K, 3].

        ``time_gate`` [N] (0/1, optional) multiplies the per-Gaussian time terms (``dopacity``,
        ``dsh0``, ``dshN``): a Gaussian with gate 0 has the same opacity and colour at every
        time (up to the deformation field).
        """
        s = self.splats
        w = 2.0 * t - 1.0
        if time_gate is not None:
            w = w * time_gate.to(s["means"])

        def change(name: str, base: torch.Tensor) -> torch.Tensor:
            if name not in s:
                return base
            d = s[name]
            return base + (w.view((-1,) + (1,) * (d.dim() - 1)) if torch.is_tensor(w) else w) * d

        out = {"means": s["means"], "scales": s["scales"], "quats": s["quats"],
               "opacities": change("dopacity", s["opacities"])}
        sh0, shN = change("dsh0", s["sh0"]), change("dshN", s["shN"])
        sh_delta = None
        if self.deforming and len(self):
            for name, d in self.deformation(s["means"], t).items():
                if name == "sh":
                    sh_delta = d
                else:
                    out[name] = out[name] + d
        if sh_delta is not None and sh_delta.shape[1] == sh0.shape[1]:
            sh0, sh_delta = sh0 + sh_delta, None  # the usual case: the colour head moves sh0
        out["sh"] = torch.cat([sh0, shN], dim=1)  # [N, K, 3]
        if sh_delta is not None:
            k = sh_delta.shape[1]
            out["sh"] = torch.cat([out["sh"][:, :k] + sh_delta, out["sh"][:, k:]], dim=1)
        return out

    @torch.no_grad()
    def apply_time_gate(self, time_gate: torch.Tensor) -> None:
        """Fold a gate into the parameters: the time terms of Gaussians with gate 0 become 0,
        so ``at_time(t)`` equals ``at_time(t, time_gate)`` afterwards."""
        for name in TIME_TERMS:
            if name in self.splats:
                d = self.splats[name]
                d.mul_(time_gate.to(d).view((-1,) + (1,) * (d.dim() - 1)))

    def opacity_change(self, time_gate: torch.Tensor | None = None,
                       scale: float = 0.0) -> torch.Tensor | None:
        """Mean per-Gaussian price of the opacity change ``dopacity`` (logit units; scalar,
        differentiable) over the Gaussians whose change is learnt (``time_gate`` [N] 0/1; all
        without a gate): ``|dopacity|``, or with ``scale`` s > 0 ``s log(1 + |dopacity| / s)``
        (the same slope at no change, growing only logarithmically beyond s). None when the
        model has no opacity change term."""
        if "dopacity" not in self.splats:
            return None
        d = self.splats["dopacity"].abs()
        if scale > 0:
            d = scale * torch.log1p(d / scale)
        if time_gate is None:
            return d.mean()
        gate = time_gate.to(d)
        return (d * gate).sum() / gate.sum().clamp(min=1)

    def at_time(self, t, time_gate: torch.Tensor | None = None) -> Gaussians:
        """Deformed, activated Gaussians at time t (see :class:`Gaussians`); differentiable.
        ``time_gate``: see :meth:`raw_at_time`."""
        r = self.raw_at_time(t, time_gate)
        q = r["quats"]
        spec = env = None
        if self.environment is not None:
            spec = torch.sigmoid(self.splats["reflectivity"])
            env = functools.partial(self.environment.radiance, t=t)
        return Gaussians(means=r["means"],
                         quats=q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12),
                         scales=torch.exp(r["scales"]),
                         opacities=torch.sigmoid(r["opacities"]),
                         sh=r["sh"], sh_degree=int(self.active_sh_degree),
                         reflectivity=spec, environment=env)


# -------------------------------------------------------------------- files


def save_model(model: GaussianModel4D, path: str | os.PathLike, meta: dict | None = None) -> None:
    """Write ``model.pt`` atomically (see module docstring for the layout)."""
    blob = {"format": FORMAT, "version": VERSION, "config": model.config(),
            "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
            "meta": meta or {}}
    save_torch(blob, path)


def load_model(path: str | os.PathLike, device: torch.device | str = "cpu") -> GaussianModel4D:
    """Load a ``model.pt`` written by :func:`save_model` onto ``device`` (eval mode).

    The file's ``meta`` dict is available as ``model.meta``. Raises :class:`ModelFileError`
    naming the file when it is missing or not a gdiff 4D Gaussian model.
    """
    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"{path}: model file not found; run the fit stage first")
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises several types for corrupt files
        raise ModelFileError(f"{path}: cannot be read as a model file ({e}); "
                             "delete it and rerun the fit stage") from None
    if not isinstance(blob, dict) or blob.get("format") != FORMAT:
        raise ModelFileError(f"{path}: not a gdiff 4D Gaussian model (no '{FORMAT}' header)")
    if blob.get("version", 0) > VERSION:
        raise ModelFileError(f"{path}: written by a newer gdiff (model version "
                             f"{blob['version']} > {VERSION}); update gdiff")
    model = GaussianModel4D.from_state(blob["config"], blob["state_dict"])
    model.meta = blob.get("meta", {})
    return model.to(device).eval()
