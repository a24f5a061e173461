"""The partition model (fitted 4D Gaussians + change head): rendering change maps at any
camera and time, saving and loading ``partition/model.pt``.

Conventions: see :mod:`gdiff.partition`.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..cameras import Camera
from ..device import resolve_device
from ..errors import ModelFileError
from ..io import save_torch
from ..splat.model import GaussianModel4D
from .gate import gate_before_map
from .head import ChangeHead, change_probability
from .options import PartitionOptions
from .render import render_features

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
        before_gate: quantile of :func:`gdiff.partition.gate.gate_before_map` applied to the
            t=0 map in the union map (0 = no gate).
    """

    def __init__(self, fit, head: ChangeHead, camera, background=None, threshold: float = 0.5,
                 before_gate: float = 0.0):
        super().__init__()
        if head.n != len(fit):
            raise ValueError(f"head has {head.n} encodings but the model {len(fit)} Gaussians")
        self.fit = fit
        self.head = head
        self.camera = camera
        bg = torch.zeros(3) if background is None else torch.as_tensor(background).float()
        self.register_buffer("background", bg.reshape(3).clone())
        self.threshold = float(threshold)
        self.before_gate = float(before_gate)

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
                      with_image: bool = False, before_gate: float | None = None
                      ) -> dict[str, np.ndarray | None]:
    """The change map of a viewpoint.

    Args:
        pmodel: from :func:`load_partition_model` or :func:`train_partition`.
        camera: :class:`gdiff.cameras.Camera` (any pose and intrinsics).
        t: time in [0, 1], or None for the union of t = 0 (what was there and changed) and
            t = 1 (what is there and is new). With ``pmodel.before_gate`` the t = 0 map
            counts in the union only where the two times render differently
            (:func:`gdiff.partition.gate.gate_before_map`).
        with_image: also return the rendered colour image(s).
        before_gate: the gate's quantile for this map (0 = the plain union); None = the
            model's ``before_gate``.
    Returns:
        dict of numpy arrays: ``prob`` [H, W] float32 in [0, 1] (for t=None the per-pixel max of
        the two times, where gated ``prob_t1``), ``mask`` [H, W] bool
        (``prob > pmodel.threshold``), ``prob_t0`` and ``prob_t1`` (None when that time was not
        rendered) and, with ``with_image``,
        ``image`` [H, W, 3] float32 sRGB (the render at ``t``; for t=None at t=0) plus
        ``image_t0`` / ``image_t1``.
    """
    times = [0.0, 1.0] if t is None else [float(t)]
    if not all(0.0 <= x <= 1.0 for x in times):
        raise ValueError(f"t must lie in [0, 1], got {t}")
    quantile = pmodel.before_gate if before_gate is None else float(before_gate)
    gate = t is None and quantile > 0
    res = {}
    for x in times:
        r = pmodel.render(camera, x, with_rgb=with_image or gate)
        res[x] = {k: v.detach().float().cpu().numpy() for k, v in r.items()}
    out: dict[str, np.ndarray | None] = {
        "prob_t0": res[0.0]["prob"] if 0.0 in res else None,
        "prob_t1": res[1.0]["prob"] if 1.0 in res else None,
    }
    if t is None:
        out["prob"] = np.maximum(out["prob_t0"], out["prob_t1"])
        if gate:
            keep = gate_before_map(out["prob_t0"], out["prob_t1"], res[0.0]["rgb"],
                                   res[1.0]["rgb"], res[0.0]["alpha"], res[1.0]["alpha"],
                                   pmodel.threshold, quantile)
            out["prob"] = np.where(keep, out["prob"], out["prob_t1"])
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
    fit = pmodel.fit
    return {"format": FORMAT, "version": VERSION,
            "fit": {"config": fit.config(),
                    "state_dict": {k: v.detach().cpu() for k, v in fit.state_dict().items()},
                    "meta": getattr(fit, "meta", {})},
            "head": {k: v.detach().cpu() for k, v in pmodel.head.state_dict().items()},
            "camera": _camera_to_dict(pmodel.camera),
            "background": pmodel.background.detach().cpu().tolist(),
            "threshold": pmodel.threshold,
            "before_gate": pmodel.before_gate,
            "options": dataclasses.asdict(options) if options is not None else {}}


def save_partition_model(pmodel: PartitionModel, path, options: PartitionOptions | None = None
                         ) -> None:
    """Write the partition ``model.pt`` atomically (format ``gdiff.PartitionModel``)."""
    save_torch(partition_blob(pmodel, options), path)


def load_partition_model(path, device="auto") -> PartitionModel:
    """Load a partition ``model.pt`` onto ``device`` (``auto``/``cpu``/``cuda`` or a
    ``torch.device``), in eval mode. Raises :class:`gdiff.errors.ModelFileError` naming the
    file when it is missing or not a partition model."""
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
    pm = PartitionModel(fit, head, cam, blob.get("background"), blob.get("threshold", 0.5),
                        blob.get("before_gate", 0.0))
    return pm.to(device).eval()
