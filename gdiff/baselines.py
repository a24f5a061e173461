"""Change-map methods scored side by side by the evaluate stage.

Each factory returns a *method*: a callable ``f(view) -> Prediction | bool ndarray [H, W]``
taking an :class:`gdiff.evaluate.EvalView` (eval before/after images, eval camera, GT mask).

* :func:`pixel_diff_method` — C-NeRF-style appearance difference: per-pixel absolute colour
  difference of the before and after images, Gaussian blur, Otsu threshold (OpenCV).
* :func:`idcompare_method` — instance-ID comparison of the eval pair itself (segment + track
  the two images, compare IDs) without the Gaussian partition: ``gdiff.compare``.
* :func:`evidence3d_method` — the compare stage's 3D change evidence alone (the voxels whose
  surface appeared, vanished or, under the same light, changed appearance:
  ``gdiff.compare.geometry``), seen from the eval camera through the fitted model's depth at
  t=0 and t=1; no learning. It shows what the 3D evidence contributes to the partition.
* :func:`render_diff_method` — the fitted 4D model alone: :func:`pixel_diff` of the model
  rendered at the eval camera at t=0 and t=1 (no segmentation, IDs or learning). It shows how
  much of a change the fit itself holds, from any viewpoint, before the later stages judge it.
* :func:`partition_method` — the learned change map rendered by the partition model at the
  eval camera: ``gdiff.partition``.

The stage modules are imported lazily, so the metric code never depends on them. A method that
cannot run on a view (e.g. a view without a before image and no renderer to stand in for it)
raises :class:`MethodNotApplicable`; the view is then skipped for that method only.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable

import cv2
import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from .evaluate import EvalView

log = logging.getLogger("gdiff.baselines")


class MethodNotApplicable(Exception):
    """The method has no input for this view (the evaluate stage skips the view for it)."""


@dataclass
class Prediction:
    """A method's output for one view: ``mask`` bool [H, W] and optional ``prob`` float [H, W]
    in [0, 1] (used to rank boxes for AP; without it boxes are ranked by area)."""

    mask: np.ndarray
    prob: np.ndarray | None = None


def as_prediction(out: Any) -> Prediction:
    """Normalise a method's return value (mask array, ``(mask, prob)``, dict or Prediction)."""
    if isinstance(out, Prediction):
        return out
    if isinstance(out, dict):
        return Prediction(np.asarray(out["mask"]) > 0,
                          None if out.get("prob") is None else _np(out["prob"]))
    if isinstance(out, tuple):
        return Prediction(_np(out[0]) > 0, None if out[1] is None else _np(out[1]))
    return Prediction(_np(out) > 0)


def _np(x) -> np.ndarray:
    if hasattr(x, "detach"):  # torch tensor on any device
        x = x.detach().cpu().numpy()
    x = np.asarray(x)
    return x[..., 0] if x.ndim == 3 and x.shape[-1] == 1 else x


# --------------------------------------------------------------------------- pixel difference


def difference_map(rgb0: np.ndarray, rgb1: np.ndarray, blur_sigma: float = 2.0) -> np.ndarray:
    """Blurred per-pixel colour difference in [0, 1], float32 [H, W].

    ``rgb0``/``rgb1``: float [H, W, 3] in [0, 1] (sRGB-encoded). The difference is the largest
    absolute channel difference; a Gaussian blur of ``blur_sigma`` pixels (0 = none) removes
    single-pixel noise and small misalignments.
    """
    rgb0 = np.asarray(rgb0, dtype=np.float32)
    rgb1 = np.asarray(rgb1, dtype=np.float32)
    if rgb0.shape != rgb1.shape:
        raise ValueError(f"before image {rgb0.shape} and after image {rgb1.shape} differ in size")
    d = np.abs(rgb1 - rgb0)
    d = d.max(axis=2) if d.ndim == 3 else d
    if blur_sigma > 0:
        d = cv2.GaussianBlur(d, (0, 0), sigmaX=float(blur_sigma))
    return np.clip(d, 0.0, 1.0)


def otsu_mask(diff: np.ndarray, min_threshold: float = 0.05) -> tuple[np.ndarray, float]:
    """Otsu threshold of a [0, 1] map, floored at ``min_threshold``: ``(mask, threshold)``.

    Otsu always splits a histogram in two, even pure noise; the floor keeps a pair without any
    real difference from being half "changed".
    """
    d8 = np.round(np.clip(diff, 0.0, 1.0) * 255.0).astype(np.uint8)
    t, _ = cv2.threshold(d8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    thr = max(float(t) / 255.0, float(min_threshold))
    return diff > thr, thr


def pixel_diff(rgb0: np.ndarray, rgb1: np.ndarray, blur_sigma: float = 2.0,
               min_threshold: float = 0.05) -> Prediction:
    """Change mask of an image pair by difference + blur + Otsu; ``prob`` is the difference."""
    d = difference_map(rgb0, rgb1, blur_sigma)
    mask, _ = otsu_mask(d, min_threshold)
    return Prediction(mask, d)


Renderer = Callable[[Any, float], np.ndarray]  # (Camera, t) -> rgb float [H, W, 3]


def _pair(view: "EvalView", render: Renderer | None) -> tuple[np.ndarray, np.ndarray]:
    """The view's before and after images; a missing one is rendered by ``render`` at its
    time (needs the eval camera), else :class:`MethodNotApplicable`."""
    imgs = []
    for t, have in ((0, view.before), (1, view.after)):
        if have is not None:
            imgs.append(view.read_image(t))
        elif render is not None and view.camera is not None:
            cam = view.camera_at_gt_size()
            imgs.append(np.asarray(render(cam, float(t)), dtype=np.float32))
        else:
            raise MethodNotApplicable(
                f"view {view.name} has no eval {'before' if t == 0 else 'after'} image"
                + ("" if render is None else " and no eval camera to render it from"))
    return imgs[0], imgs[1]


def pixel_diff_method(blur_sigma: float = 2.0, min_threshold: float = 0.05,
                      render: Renderer | None = None) -> Callable[["EvalView"], Prediction]:
    """C-NeRF-style baseline on the eval pair (see :func:`pixel_diff`).

    ``render(camera, t) -> rgb [H, W, 3]`` (optional) stands in for a missing eval image, e.g.
    the 4D model's render at ``t = 0`` for datasets that give only post-change eval views.
    """

    def method(view: "EvalView") -> Prediction:
        rgb0, rgb1 = _pair(view, render)
        return pixel_diff(rgb0, rgb1, blur_sigma, min_threshold)

    method.__name__ = "pixel_diff"
    return method


# ------------------------------------------------------------------------------- ID compare


def idcompare_method(detect: Callable | None = None, render: Renderer | None = None,
                     depth: Renderer | None = None, **kwargs) -> Callable[["EvalView"], Prediction]:
    """Instance-ID comparison of the eval pair, without the partition model.

    Calls ``detect(rgb0, rgb1, depth0=..., depth1=..., **kwargs) -> (mask_t0, mask_t1)``
    (default: ``gdiff.compare.detect_changes_pair``, imported on first use, which also gets the
    eval camera's ``K`` when known; pass ``segment_options=``, ``track_options=``,
    ``options=`` through ``kwargs``) and returns the union of the two masks (the GT marks
    changed objects visible before *or* after).

    ``depth(camera, t) -> z [H, W]`` (optional; camera-frame z in world units, 0 or inf where
    empty): the eval photos have no depth, so the fitted model's depth at the eval camera at
    t=0 and t=1 stands in for it (segment boundaries and the compare stage's depth evidence, which
    ignores a shadow or a highlight that moved). Without it, or for a view without an eval camera,
    the pair is compared on colour alone.
    """

    def method(view: "EvalView") -> Prediction:
        fn, kw = detect, dict(kwargs)
        cam = None
        if view.camera is not None:
            cam = view.camera_at_gt_size()
        if fn is None:
            from .compare import detect_changes_pair  # lazy: stage module

            fn = detect_changes_pair
        rgb0, rgb1 = _pair(view, render)
        d0 = d1 = None
        if cam is not None:
            h, w = rgb0.shape[:2]
            if (cam.width, cam.height) != (w, h):  # photos at another size than the GT mask
                cam = cam.scaled(w / cam.width)
                cam.width, cam.height = w, h
            if detect is None:
                kw.setdefault("K", cam.K)
            if depth is not None:
                d0, d1 = (np.asarray(depth(cam, t), np.float32) for t in (0.0, 1.0))
        m0, m1 = fn(rgb0, rgb1, depth0=d0, depth1=d1, **kw)
        return Prediction(_np(m0).astype(bool) | _np(m1).astype(bool))

    method.__name__ = "idcompare"
    return method


# -------------------------------------------------------------------------------- partition


def evidence3d_method(evidence: Any, depth: Callable[[Any, float], np.ndarray]
                      ) -> Callable[["EvalView"], Prediction]:
    """The 3D change evidence at the eval camera: ``evidence`` is the compare stage's
    ``change/evidence3d.npz`` (path) or its contents (:func:`gdiff.compare.geometry.read_evidence`);
    ``depth(camera, t)`` renders the fitted model's z-depth [H, W]. A pixel is changed when its
    surface at t=0 lies in a voxel changed at t=0, or at t=1 in one changed at t=1."""
    from .compare.geometry import evidence_masks, read_evidence  # lazy: stage module

    ev = read_evidence(evidence) if not isinstance(evidence, dict) else evidence

    def method(view: "EvalView") -> Prediction:
        if view.camera is None:
            raise MethodNotApplicable(f"view {view.name} has no eval camera in cameras.json")
        cam = view.camera_at_gt_size()
        m0, m1 = evidence_masks(ev, cam, depth(cam, 0.0), depth(cam, 1.0))
        return Prediction(m0 | m1)

    method.__name__ = "evidence3d"
    return method


def render_diff_method(render: Renderer, blur_sigma: float = 2.0, min_threshold: float = 0.05
                       ) -> Callable[["EvalView"], Prediction]:
    """:func:`pixel_diff` of the fitted model's renders at the eval camera at t=0 and t=1
    (``render(camera, t) -> rgb [H, W, 3]``, at the ground-truth mask's size)."""

    def method(view: "EvalView") -> Prediction:
        if view.camera is None:
            raise MethodNotApplicable(f"view {view.name} has no eval camera in cameras.json")
        cam = view.camera_at_gt_size()
        return pixel_diff(render(cam, 0.0), render(cam, 1.0), blur_sigma, min_threshold)

    method.__name__ = "render_diff"
    return method


def partition_method(pmodel: Any, render_change_map: Callable | None = None,
                     t: float | None = None) -> Callable[["EvalView"], Prediction]:
    """The learned change map at the eval camera.

    Calls ``render_change_map(pmodel, camera, t=t)`` (default
    ``gdiff.partition.render_change_map``) and uses its ``"mask"`` (and ``"prob"`` when
    present, for box ranking). The camera is scaled to the ground-truth mask's size.
    """

    def method(view: "EvalView") -> Prediction:
        fn = render_change_map
        if fn is None:
            from .partition import render_change_map as fn  # lazy: stage module
        if view.camera is None:
            raise MethodNotApplicable(f"view {view.name} has no eval camera in cameras.json")
        out = fn(pmodel, view.camera_at_gt_size(), t=t)
        prob = out.get("prob") if isinstance(out, dict) else None
        return Prediction(_np(out["mask"]) > 0, None if prob is None else _np(prob))

    method.__name__ = "partition"
    return method
