"""Evaluate stage: score change-map methods side by side at a scene's eval viewpoints.

Eval views of a scene folder (matched by file stem)::

    eval/masks/NAME.png          ground-truth change mask (255 = changed), required
    eval/before/NAME.*           image before the change at that viewpoint  } at least one;
    eval/after/NAME.*            image after the change, same viewpoint     } usually both
    eval/mask_before/NAME.png    optional: the part of the mask from objects present before
    eval/mask_after/NAME.png     optional: the part from objects present after

The ground truth marks every pixel where a changed object is visible in the before *or* the after
state (see docs/datasets.md for how each public dataset maps onto this). Datasets that give only
post-change eval images produce views without ``eval/before``; methods that need a before image
then use a renderer of the fitted model at ``t = 0`` when the workflow passes one, or skip the
view (logged).

Outputs in ``out_dir`` (``results/<scene>/eval/``), all written atomically:

* ``metrics.csv`` — one row per (view, method): ``scene, view, method, P, R, F1, IoU, TP, FP,
  FN, box_P, box_R, box_F1, box_AP, box_TP, box_FP, box_FN, seconds`` (see
  :mod:`gdiff.metrics` for definitions and the NaN convention);
* ``boxes.csv`` — every predicted and ground-truth box (for AP pooled over views);
* ``scene_summary.csv`` — per method: mean over views and pooled figures;
* ``maps/<method>/NAME.png`` — each method's binary change map;
* ``overlays/NAME.png`` — one row per method: image | prediction | ground truth | TP (green),
  FP (red), FN (blue), with the view's F1/IoU written on it.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np
import pandas as pd

from .baselines import (MethodNotApplicable, Prediction, as_prediction, idcompare_method,
                        partition_method, pixel_diff_method)
from .cameras import Camera, image_root, load_cameras
from .errors import ConfigError, SceneError
from .io import read_image, read_mask, write_csv, write_image, write_mask
from .scene import list_images
from .log import progress
from .metrics import aggregate, score_view

log = logging.getLogger("gdiff.evaluate")

METHODS = ("pixel_diff", "idcompare", "partition")
METRIC_COLUMNS = ["scene", "view", "method", "P", "R", "F1", "IoU", "TP", "FP", "FN",
                  "box_P", "box_R", "box_F1", "box_AP", "box_TP", "box_FP", "box_FN", "seconds"]


@dataclass
class EvalOptions:
    """Options of the ``evaluate`` config section."""

    methods: list[str] = field(default_factory=lambda: list(METHODS))
    """Methods to score side by side: any of pixel_diff, idcompare, partition."""
    box_iou: float = 0.5
    """IoU a predicted box needs with a ground-truth box to count as a detection."""
    box_min_area: float = 0.0005
    """Connected regions smaller than this fraction of the image are not boxes (pred and GT)."""
    pixel_blur_sigma: float = 2.0
    """pixel_diff: Gaussian blur (pixels) of the colour difference before Otsu."""
    pixel_min_threshold: float = 0.05
    """pixel_diff: lowest threshold on the [0, 1] difference (Otsu splits even pure noise)."""
    idcompare_depth: bool = False
    """idcompare: give the eval pair the fitted model's depth at the eval camera at t=0 and t=1
    (photos have no depth). Off by default: on the path-traced bench scenes the fitted depth at
    novel eval views added false evidence (pooled F1 0.885 -> 0.565 and 0.288 -> 0.202)."""
    overlays: bool = True
    """Write overlays/NAME.png (image | prediction | GT | TP/FP/FN per method)."""
    overlay_max_side: int = 400
    """Longest side of each overlay panel in pixels (panels are shrunk, never enlarged)."""

    def __post_init__(self):
        bad = [m for m in self.methods if m not in METHODS]
        if bad:
            raise ValueError(f"methods: unknown {', '.join(bad)}; choose from {', '.join(METHODS)}")
        if not 0.0 < self.box_iou <= 1.0:
            raise ValueError("box_iou must lie in (0, 1]")
        if not 0.0 <= self.box_min_area < 1.0:
            raise ValueError("box_min_area is a fraction of the image and must lie in [0, 1)")


# ------------------------------------------------------------------------------------ views


@dataclass
class EvalView:
    """One eval viewpoint: ground-truth mask, before/after images (either may be missing) and
    the eval camera (OpenCV c2w, intrinsics of the eval images) when ``cameras.json`` has it."""

    name: str
    mask: Path
    before: Path | None = None
    after: Path | None = None
    camera: Camera | None = None
    mask_before: Path | None = None
    mask_after: Path | None = None
    _gt: np.ndarray | None = field(default=None, repr=False)

    def read_gt(self) -> np.ndarray:
        """Ground-truth change mask, bool [H, W]."""
        if self._gt is None:
            self._gt = read_mask(self.mask)
        return self._gt

    def read_image(self, t: int) -> np.ndarray:
        """Eval image at time ``t`` (0 before, 1 after), float32 [H, W, 3] in [0, 1], resized
        to the mask's size if it differs."""
        path = self.before if t == 0 else self.after
        if path is None:
            raise MethodNotApplicable(f"view {self.name}: no eval {'before' if t == 0 else 'after'}"
                                      " image")
        img = read_image(path)
        h, w = self.read_gt().shape
        if img.shape[:2] != (h, w):
            img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
        return img

    def display_image(self) -> np.ndarray:
        """The after image (else the before image) for overlays, [H, W, 3]."""
        return self.read_image(1 if self.after is not None else 0)

    def camera_at_gt_size(self) -> Camera:
        """The eval camera scaled to the ground-truth mask's size."""
        if self.camera is None:
            raise MethodNotApplicable(f"view {self.name} has no eval camera")
        h, w = self.read_gt().shape
        cam = self.camera
        if (cam.width, cam.height) != (w, h):
            cam = cam.scaled(w / cam.width)
            cam.width, cam.height = w, h
        return cam


def _by_stem(folder: Path) -> dict[str, Path]:
    """The images of ``folder`` (:func:`gdiff.scene.list_images`) keyed by file stem."""
    out: dict[str, Path] = {}
    for p in list_images(folder):
        if p.stem in out:
            raise SceneError(f"{folder}: two files with the stem {p.stem!r} ({out[p.stem].name},"
                             f" {p.name}); keep one")
        out[p.stem] = p
    return out


def find_eval_views(scene_dir: str | Path, cameras_json: str | Path | None = None
                    ) -> list[EvalView]:
    """The eval views of a scene folder (layout in the module docstring), sorted by name.

    ``cameras_json`` (the poses stage's ``cameras.json``) supplies the eval cameras: frames of
    set ``eval_after`` (preferred) or ``eval_before`` whose image is the view's image.
    """
    root = Path(scene_dir)
    ev = root / "eval"
    masks = _by_stem(ev / "masks")
    before, after = _by_stem(ev / "before"), _by_stem(ev / "after")
    if not masks:
        raise SceneError(f"{ev}/masks: no ground-truth masks; the evaluate stage needs "
                         "eval/masks/NAME.png with eval/before/NAME.* and/or eval/after/NAME.*")
    orphans = sorted((set(before) | set(after)) - set(masks))
    if orphans:
        raise SceneError(f"{ev}: eval image(s) {', '.join(orphans[:5])} have no mask in "
                         "eval/masks/ (same file stem); add the masks or remove the images")
    cams: dict[str, Camera] = {}
    if cameras_json is not None:
        for c in load_cameras(cameras_json):
            if c.set in ("eval_before", "eval_after") and c.image:
                cams[(c.set, Path(c.image).stem)] = c
    mb, ma = _by_stem(ev / "mask_before"), _by_stem(ev / "mask_after")
    views = []
    for stem, mpath in sorted(masks.items()):
        b, a = before.get(stem), after.get(stem)
        if b is None and a is None:
            raise SceneError(f"{mpath}: mask without an image; add eval/before/{stem}.* and/or "
                             f"eval/after/{stem}.*, or remove the mask")
        cam = cams.get(("eval_after", stem)) if a is not None else None
        cam = cam or (cams.get(("eval_before", stem)) if b is not None else None)
        views.append(EvalView(stem, mpath, b, a, cam, mb.get(stem), ma.get(stem)))
    if cameras_json is not None:
        missing = [v.name for v in views if v.camera is None]
        if missing:
            log.warning("%s: no eval camera for view(s) %s; the partition method skips them",
                        cameras_json, ", ".join(missing[:10]))
    return views


# ---------------------------------------------------------------------------------- methods


def build_methods(options: EvalOptions, pmodel: Any = None, render: Callable | None = None,
                  detect: Callable | None = None, depth: Callable | None = None,
                  **idcompare_kwargs) -> dict[str, Callable]:
    """The methods named in ``options.methods``, ready for :func:`evaluate_scene`.

    ``pmodel``: the trained partition model (needed for ``partition``); ``render(camera, t)``:
    optional renderer standing in for missing eval images; ``depth(camera, t)``: optional depth
    renderer giving ``idcompare`` the model's depth (``options.idcompare_depth``); ``detect``: override of
    ``gdiff.change.detect_changes_pair`` for ``idcompare``; ``idcompare_kwargs`` (e.g.
    ``segment_options=``) are passed on to it.
    """
    out: dict[str, Callable] = {}
    for name in options.methods:
        if name == "pixel_diff":
            out[name] = pixel_diff_method(options.pixel_blur_sigma, options.pixel_min_threshold,
                                          render=render)
        elif name == "idcompare":
            out[name] = idcompare_method(detect=detect, render=render,
                                         depth=depth if options.idcompare_depth else None,
                                         **idcompare_kwargs)
        elif name == "partition":
            if pmodel is None:
                raise ConfigError("evaluate.methods lists 'partition' but no partition model "
                                  "was given")
            out[name] = partition_method(pmodel)
    return out


def model_renderer(model: Any) -> Callable[[Camera, float], np.ndarray]:
    """``render(camera, t) -> rgb float32 [H, W, 3]`` from a fitted 4D model
    (``gdiff.splat.render.render``, imported on first use)."""

    def render(camera: Camera, t: float) -> np.ndarray:
        import torch

        from .splat.render import render as splat_render  # lazy: stage module

        with torch.no_grad():
            rgb = splat_render(model, [camera], t, render_mode="RGB")["rgb"]
        rgb = np.asarray(rgb.detach().cpu().numpy(), dtype=np.float32)
        return np.clip(rgb[0] if rgb.ndim == 4 else rgb, 0.0, 1.0)

    return render


def model_depth(model: Any) -> Callable[[Camera, float], np.ndarray]:
    """``depth(camera, t) -> z float32 [H, W]`` (camera-frame z, world units) from a fitted 4D
    model: the expected depth, as the render stage writes it to the EXR ``Z`` channel."""

    def depth(camera: Camera, t: float) -> np.ndarray:
        import torch

        from .splat.render import render as splat_render  # lazy: stage module

        with torch.no_grad():
            out = splat_render(model, [camera], t, render_mode="ED")
        return out["depth"].detach().cpu().numpy()[0, ..., 0].astype(np.float32)

    return depth


def evaluate_workflow_scene(scene_dir: str | Path, cameras_json: str | Path,
                            partition_model: str | Path, out_dir: str | Path, scene_name: str,
                            options: EvalOptions, segment_options: dict | None = None,
                            device: str = "auto") -> pd.DataFrame:
    """The ``evaluate`` rule: load the partition model (whose fitted 4D model also renders any
    eval image a dataset lacks) and score every method of ``options.methods`` side by side."""
    from .options import from_config
    from .partition import load_partition_model  # lazy: stage module
    from .segment import SegmentOptions

    pmodel = load_partition_model(partition_model, device)
    seg = from_config(SegmentOptions, segment_options, "segment")
    methods = build_methods(options, pmodel=pmodel, render=model_renderer(pmodel.fit),
                            depth=model_depth(pmodel.fit), segment_options=seg)
    return evaluate_scene(scene_dir, cameras_json, out_dir, scene_name, methods, options)


# ---------------------------------------------------------------------------------- scoring


def evaluate_scene(scene_dir: str | Path, cameras_json: str | Path | None, out_dir: str | Path,
                   scene_name: str, methods: dict[str, Callable], options: EvalOptions
                   ) -> pd.DataFrame:
    """Score every method at every eval view; write the outputs listed in the module docstring.

    ``methods``: name -> ``f(view: EvalView) -> bool mask [H, W]`` (or ``(mask, prob)``,
    ``{"mask", "prob"}``, :class:`gdiff.baselines.Prediction`); a prediction of another size
    than the ground truth is resized (nearest) with a warning. Returns the metrics table.
    """
    out_dir = Path(out_dir)
    views = find_eval_views(image_root(scene_dir, cameras_json), cameras_json)
    rows, box_frames = [], []
    for view in progress(views, desc=f"evaluate {scene_name}"):
        gt = view.read_gt()
        h, w = gt.shape
        min_area = int(math.ceil(options.box_min_area * h * w))
        preds: dict[str, Prediction] = {}
        for name, fn in methods.items():
            t0 = time.perf_counter()
            try:
                pred = as_prediction(fn(view))
            except MethodNotApplicable as e:
                log.info("%s: %s skipped (%s)", scene_name, name, e)
                continue
            seconds = time.perf_counter() - t0
            pred = _fit_to(pred, (h, w), f"{name} at view {view.name}")
            scores, boxes = score_view(pred.mask, gt, pred.prob, options.box_iou, min_area)
            rows.append({"scene": scene_name, "view": view.name, "method": name, **scores,
                         "seconds": seconds})
            box_frames.append(boxes.assign(scene=scene_name, view=view.name, method=name))
            write_mask(out_dir / "maps" / name / f"{view.name}.png", pred.mask)
            preds[name] = pred
        if options.overlays and preds:
            write_image(out_dir / "overlays" / f"{view.name}.png",
                        overlay_panel(view.display_image(), preds, gt, options.overlay_max_side,
                                      [r for r in rows if r["view"] == view.name]))
    df = pd.DataFrame(rows, columns=METRIC_COLUMNS)
    box_cols = ["scene", "view", "method", "kind", "x0", "y0", "x1", "y1", "score", "matched",
                "iou"]
    frames = [f for f in box_frames if len(f)]
    boxes = (pd.concat(frames, ignore_index=True)[box_cols] if frames
             else pd.DataFrame(columns=box_cols))
    write_csv(out_dir / "metrics.csv", df)
    write_csv(out_dir / "boxes.csv", boxes)
    write_csv(out_dir / "scene_summary.csv", aggregate(df, boxes) if len(df) else
              pd.DataFrame(columns=["scene", "method"]))
    for m, g in df.groupby("method"):
        log.info("%s %s: F1 %.3f IoU %.3f (mean of %d views)", scene_name, m,
                 g["F1"].mean(), g["IoU"].mean(), len(g))
    return df


def _fit_to(pred: Prediction, shape: tuple[int, int], what: str) -> Prediction:
    mask = np.asarray(pred.mask)
    if mask.ndim != 2:
        raise ValueError(f"{what}: prediction must be a [H, W] mask, got shape {mask.shape}")
    if mask.shape == shape:
        return pred
    log.warning("%s: prediction %s resized to the ground truth's %s", what, mask.shape, shape)
    h, w = shape
    mask = cv2.resize(mask.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
    prob = pred.prob
    if prob is not None:
        prob = cv2.resize(np.asarray(prob, np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
    return Prediction(mask, prob)


# --------------------------------------------------------------------------------- overlays

_TP, _FP, _FN = (0.1, 0.8, 0.1), (0.9, 0.1, 0.1), (0.15, 0.35, 1.0)


def _tint(img: np.ndarray, mask: np.ndarray, colour, alpha: float = 0.55) -> np.ndarray:
    out = img.copy()
    out[mask] = (1 - alpha) * out[mask] + alpha * np.asarray(colour, np.float32)
    return out


def _label(img: np.ndarray, text: str, row: int = 0) -> np.ndarray:
    u8 = np.ascontiguousarray((np.clip(img, 0, 1) * 255).astype(np.uint8))
    scale = max(0.3, img.shape[1] / 800.0)
    y = int(round(30 * scale)) * (row + 1)
    (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    x0, y0 = 2, max(0, y - th - 2)
    u8[y0:y + base + 1, x0:x0 + tw + 4] //= 3  # dark backdrop keeps the text readable
    cv2.putText(u8, text, (4, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1,
                cv2.LINE_AA)
    return u8.astype(np.float32) / 255.0


def error_map(image: np.ndarray, pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Dimmed grey image with TP green, FP red, FN blue; float [H, W, 3]."""
    grey = np.repeat(image.mean(axis=2, keepdims=True), 3, axis=2) * 0.5
    out = grey.copy()
    for m, c in ((pred & gt, _TP), (pred & ~gt, _FP), (~pred & gt, _FN)):
        out[m] = c
    return out


def overlay_panel(image: np.ndarray, preds: dict[str, Prediction], gt: np.ndarray,
                  max_side: int = 400, rows: list[dict] | None = None) -> np.ndarray:
    """One row per method: image | prediction | ground truth | TP/FP/FN; float [H', W', 3]."""
    gt = np.asarray(gt, bool)
    h, w = gt.shape
    s = min(1.0, max_side / max(h, w))
    size = (max(1, int(round(w * s))), max(1, int(round(h * s))))
    scores = {r["method"]: r for r in rows or []}
    lines = []
    for name, p in preds.items():
        mask = np.asarray(p.mask, bool)
        r = scores.get(name, {})
        f1, iou = r.get("F1", float("nan")), r.get("IoU", float("nan"))
        panels = [(image, name),
                  (_tint(image, mask, _FP), f"prediction F1 {f1:.2f} IoU {iou:.2f}"),
                  (_tint(image, gt, _FN), "ground truth"),
                  (error_map(image, mask, gt), "TP green, FP red, FN blue")]
        lines.append(np.concatenate(
            [_label(cv2.resize(im, size, interpolation=cv2.INTER_AREA), text)
             for im, text in panels], axis=1))
    return np.concatenate(lines, axis=0)
