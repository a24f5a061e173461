"""Evaluate stage: score change-map methods side by side at a scene's eval viewpoints.

Eval views of a scene folder (matched by file stem)::

    eval/masks/NAME.png          ground-truth change mask (255 = changed), required
    eval/before/NAME.*           image before the change at that viewpoint  } at least one;
    eval/after/NAME.*            image after the change, same viewpoint     } usually both
    eval/mask_before/NAME.png    optional: the part of the mask from objects present before
    eval/mask_after/NAME.png     optional: the part from objects present after
    eval/boxes.json              optional box ground truth (below)

The ground truth marks every pixel where a changed object is visible in the before *or* the after
state (see docs/datasets.md for how each public dataset maps onto this). Datasets that give only
post-change eval images produce views without ``eval/before``; methods that need a before image
then use a renderer of the fitted model at ``t = 0`` when the workflow passes one, or skip the
view (logged).

Box ground truth (``eval/boxes.json``; many real datasets give boxes, not masks): per view a
list of boxes ``[x0, y0, x1, y1]`` in pixels of that view's image, either as
``{"NAME": [[x0, y0, x1, y1], ...], ...}`` or in the layout
``{"views": {"NAME": {"boxes_xyxy_px": [[...], ...]}, ...}}`` (extra keys ignored). ``NAME``
is an eval view (its stem, with or without extension) or a training image: a path in the scene
folder (``after/v00.png``) or a bare file name, taken from ``after/`` when it is there, else
from ``before/``. Eval views with boxes get box scores beside their mask scores; a training
image with boxes becomes a *box view* (named by its path without extension, e.g. ``after/v00``)
where only ``render_diff``, ``evidence3d`` and ``partition`` are scored, at that image's camera from
``poses/cameras.json`` (the other methods need an eval photo pair and are skipped, logged).
Box scores (:func:`gdiff.metrics.gt_box_scores`): a box is found when at least
``object_found_fraction`` of its core (the centred ``box_core`` of its width and height) is
predicted changed, and ``far_frac`` is the share of the image predicted changed farther than
``box_margin`` pixels from every box.

Outputs in ``out_dir`` (``results/<scene>/eval/``), all written atomically:

* ``metrics.csv`` — one row per (view, method): ``scene, view, method, P, R, F1, IoU, TP, FP,
  FN, box_P, box_R, box_F1, box_AP, box_TP, box_FP, box_FN, seconds, obj_N, obj_found, obj_R``
  (objects: connected regions of ``mask_before``/``mask_after``, else of ``masks``, of at least
  ``box_min_area``; see :mod:`gdiff.metrics` for definitions and the NaN convention), then
  ``gtbox_N, gtbox_found, gtbox_R, far_FP, far_N, far_frac`` (box ground truth; empty for views
  without boxes; pixel and object columns empty for box views);
* ``boxes.csv`` — every predicted and ground-truth box (for AP pooled over views; ``kind``
  ``pred`` or ``gt``) and, per method, every box of ``eval/boxes.json`` (``kind`` ``gt_box``:
  ``core`` the fraction of its core predicted changed, ``matched`` whether it is found, and at
  a training image ``judged``, the fraction of its core the compare stage could judge, from
  its ``change/<path>/judged/`` map), so a missed box shows by how much it was missed and
  whether the photos of both visits showed it at all;
* ``fit_quality.csv`` — PSNR of the fitted model at each eval view, t=0 vs ``eval/before`` and
  t=1 vs ``eval/after`` (:func:`render_quality`; written by :func:`evaluate_workflow_scene`);
* ``scene_summary.csv`` — per method: mean over views and pooled figures (``obj_R_pooled``:
  objects found over objects, all views);
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

from .baselines import (MethodNotApplicable, Prediction, as_prediction, evidence3d_method,
                        idcompare_method, partition_method, pixel_diff_method,
                        render_diff_method)
from .cameras import PHOTO_CAMERAS, Camera, image_root, load_cameras
from .errors import ConfigError, SceneError
from .io import (imread_upright, read_image, read_image_sized, read_json, read_mask, write_csv,
                 write_image, write_mask)
from .scene import list_images
from .sfm.undistort import boxes_to_pinhole
from .log import progress
from .metrics import (aggregate, gt_box_cores, gt_box_scores, object_regions, object_scores,
                      score_view)

log = logging.getLogger("gdiff.evaluate")

METHODS = ("pixel_diff", "idcompare", "render_diff", "evidence3d", "partition")
# methods that need only the eval camera (and the fitted model), not an eval photo pair
CAMERA_METHODS = ("render_diff", "evidence3d", "partition")
METRIC_COLUMNS = ["scene", "view", "method", "P", "R", "F1", "IoU", "TP", "FP", "FN",
                  "box_P", "box_R", "box_F1", "box_AP", "box_TP", "box_FP", "box_FN", "seconds",
                  "obj_N", "obj_found", "obj_R", "gtbox_N", "gtbox_found", "gtbox_R", "far_FP",
                  "far_N", "far_frac"]


@dataclass
class EvalOptions:
    """Options of the ``evaluate`` config section."""

    methods: list[str] = field(default_factory=lambda: list(METHODS))
    """Methods to score side by side: any of pixel_diff, idcompare, render_diff, evidence3d,
    partition."""
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
    object_found_fraction: float = 0.5
    """Object recall: an object (a connected region of eval/mask_before or eval/mask_after, else
    of eval/masks) counts as found in a view when at least this fraction of its pixels is
    predicted changed."""
    box_core: float = 0.5
    """Box ground truth: the centred part of a box (this fraction of its width and height) that
    must be mostly (``object_found_fraction``) predicted changed for the box to count as found."""
    box_margin: float = 25.0
    """Box ground truth: predicted change farther than this many pixels (of the view's image)
    from every box counts as flagged far from any annotated change."""
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
        if not 0.0 < self.object_found_fraction <= 1.0:
            raise ValueError("object_found_fraction must lie in (0, 1]")
        if not 0.0 < self.box_core <= 1.0:
            raise ValueError("box_core must lie in (0, 1]")
        if self.box_margin < 0:
            raise ValueError("box_margin is in pixels and must be >= 0")


# ------------------------------------------------------------------------------------ views


@dataclass
class EvalView:
    """One eval viewpoint: ground-truth mask, before/after images (either may be missing) and
    the eval camera (OpenCV c2w, intrinsics of the eval images) when ``cameras.json`` has it."""

    name: str
    mask: Path | None
    before: Path | None = None
    after: Path | None = None
    camera: Camera | None = None
    mask_before: Path | None = None
    mask_after: Path | None = None
    boxes: np.ndarray | None = None
    """Ground-truth boxes float [K, 4] ``x0, y0, x1, y1`` in pixels of ``box_size``, or None."""
    box_size: tuple[int, int] | None = None
    """``(width, height)`` of the image the boxes are given in."""
    box_px: float = 1.0
    """Pixels of ``box_size`` per pixel of the photo the boxes were drawn on (not 1 when they
    were carried into an undistorted or resampled image): ``box_margin`` is in the photo's."""
    image: Path | None = None
    """Box views (no mask): the training image the boxes belong to."""
    _gt: np.ndarray | None = field(default=None, repr=False)

    def read_gt(self) -> np.ndarray:
        """Ground-truth change mask, bool [H, W]."""
        if self.mask is None:
            raise MethodNotApplicable(f"view {self.name} has boxes only, no change mask")
        if self._gt is None:
            self._gt = read_mask(self.mask)
        return self._gt

    def shape(self) -> tuple[int, int]:
        """``(H, W)`` the view is scored at: the mask's, else the image's."""
        if self.mask is not None:
            return self.read_gt().shape
        w, h = self.box_size
        return h, w

    def boxes_at_scored_size(self) -> np.ndarray | None:
        """The ground-truth boxes scaled to :meth:`shape`, float [K, 4], or None."""
        if self.boxes is None:
            return None
        h, w = self.shape()
        bw, bh = self.box_size
        return self.boxes * np.array([w / bw, h / bh, w / bw, h / bh])

    def object_masks(self) -> list[np.ndarray]:
        """The masks whose connected regions are this view's objects, bool [H, W] each:
        ``mask_before`` and ``mask_after`` where the scene has them (a moved object is then one
        object at each place), else the change mask itself."""
        parts = [p for p in (self.mask_before, self.mask_after) if p is not None]
        if not parts:
            return [self.read_gt()]
        h, w = self.read_gt().shape
        out = []
        for p in parts:
            m = read_mask(p)
            if m.shape != (h, w):
                raise SceneError(f"{p}: size {m.shape[1]}x{m.shape[0]} differs from the change "
                                 f"mask {self.mask} ({w}x{h}); object masks must match it")
            out.append(m)
        return out

    def read_image(self, t: int) -> np.ndarray:
        """Eval image at time ``t`` (0 before, 1 after), float32 [H, W, 3] in [0, 1], resized
        to the mask's size if it differs."""
        path = self.before if t == 0 else self.after
        if path is None:
            raise MethodNotApplicable(f"view {self.name}: no eval {'before' if t == 0 else 'after'}"
                                      " image")
        h, w = self.read_gt().shape
        return read_image_sized(path, w, h)

    def display_image(self) -> np.ndarray:
        """The after image (else the before image; a box view's image) for overlays,
        [H, W, 3]."""
        if self.mask is None:
            img = read_image(self.image)
            h, w = self.shape()
            return img if img.shape[:2] == (h, w) else cv2.resize(img, (w, h))
        return self.read_image(1 if self.after is not None else 0)

    def camera_at_gt_size(self) -> Camera:
        """The eval camera scaled to the ground-truth mask's size (a box view's: its image's)."""
        if self.camera is None:
            raise MethodNotApplicable(f"view {self.name} has no eval camera")
        h, w = self.shape()
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


def find_eval_views(scene_dir: str | Path, cameras_json: str | Path | None = None,
                    original_dir: str | Path | None = None) -> list[EvalView]:
    """The eval views of a scene folder (layout in the module docstring), sorted by name.

    ``cameras_json`` (the poses stage's ``cameras.json``) supplies the eval cameras: frames of
    set ``eval_after`` (preferred) or ``eval_before`` whose image is the view's image.
    ``original_dir``: the user's scene folder when ``scene_dir`` is the poses stage's copy of
    the images (undistorted or resampled photos); ``eval/boxes.json`` is read from there when
    the copy has none. Its boxes are in the pixels of the user's photos; they are carried into
    the copy's images with the photos' own cameras the poses stage keeps beside
    ``cameras_json`` (:data:`gdiff.cameras.PHOTO_CAMERAS`, :func:`_attach_boxes`).
    """
    root = Path(scene_dir)
    ev = root / "eval"
    masks = _by_stem(ev / "masks")
    before, after = _by_stem(ev / "before"), _by_stem(ev / "after")
    boxes_json = ev / "boxes.json"
    original = None
    if not boxes_json.is_file() and original_dir is not None:
        boxes_json = Path(original_dir) / "eval" / "boxes.json"
        if Path(original_dir).resolve() != root.resolve():
            original = Path(original_dir)
    box_gt = read_boxes(boxes_json) if boxes_json.is_file() else None
    if not masks and box_gt is None:
        raise SceneError(f"{ev}/masks: no ground-truth masks; the evaluate stage needs "
                         "eval/masks/NAME.png with eval/before/NAME.* and/or eval/after/NAME.*, "
                         "or box ground truth in eval/boxes.json")
    orphans = sorted((set(before) | set(after)) - set(masks))
    if orphans:
        raise SceneError(f"{ev}: eval image(s) {', '.join(orphans[:5])} have no mask in "
                         "eval/masks/ (same file stem); add the masks or remove the images")
    cams = _cameras_by_view(cameras_json) if cameras_json is not None else {}
    photo_file = (Path(cameras_json).parent / PHOTO_CAMERAS if cameras_json is not None
                  else None)
    photo_cams = (_cameras_by_view(photo_file)
                  if original is not None and photo_file.is_file() else {})
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
    if box_gt is not None:
        views += _attach_boxes(root, views, box_gt, cams, cameras_json is not None,
                               original, photo_cams, boxes_json)
        if photo_cams:
            log.info("%s: boxes carried from the photos' pixels into the undistorted / "
                     "resampled images with the photos' cameras (%s)", boxes_json, photo_file)
    if cameras_json is not None:
        missing = [v.name for v in views if v.camera is None]
        if missing:
            log.warning("%s: no eval camera for view(s) %s; the partition method skips them",
                        cameras_json, ", ".join(missing[:10]))
    return views


def read_boxes(path: str | Path) -> dict[str, np.ndarray]:
    """``eval/boxes.json`` (either layout of the module docstring) -> ``{NAME: float [K, 4]}``.
    Raises :class:`SceneError` naming the file and the entry when a box is malformed."""
    path = Path(path)
    data = read_json(path)
    if isinstance(data, dict) and isinstance(data.get("views"), dict):
        data = data["views"]
    if not isinstance(data, dict):
        raise SceneError(f"{path}: expected an object {{NAME: [[x0, y0, x1, y1], ...]}} or "
                         "{\"views\": {NAME: {\"boxes_xyxy_px\": [...]}}}")
    out = {}
    for name, entry in data.items():
        if isinstance(entry, dict):
            entry = entry.get("boxes_xyxy_px", entry.get("boxes"))
        try:
            b = np.asarray(entry, dtype=np.float64).reshape(-1, 4)
            ok = bool(np.isfinite(b).all() and (b[:, 2] > b[:, 0]).all()
                      and (b[:, 3] > b[:, 1]).all())
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise SceneError(f"{path}: entry {name!r} is not a list of boxes [x0, y0, x1, y1] "
                             "(pixels, x1 > x0, y1 > y0)")
        out[str(name)] = b
    return out


def _image_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` of the upright image (EXIF orientation applied)."""
    img = imread_upright(path)
    if img is None:
        raise SceneError(f"{path}: cannot be read as an image")
    return int(img.shape[1]), int(img.shape[0])


def _cameras_by_view(path: str | Path) -> dict:
    """The cameras of a ``cameras.json`` by view: ``(set, stem)`` for eval images,
    ``("train", image path)`` for the others."""
    out = {}
    for c in load_cameras(path):
        if c.set in ("eval_before", "eval_after") and c.image:
            out[(c.set, Path(c.image).stem)] = c
        elif c.image:
            out[("train", Path(c.image).as_posix())] = c
    return out


def _boxes_in_image(boxes: np.ndarray, name: str, root: Path, rel: Path, key, cams: dict,
                    photo_cams: dict, original: Path | None
                    ) -> tuple[np.ndarray, tuple[int, int], float]:
    """Boxes float [K, 4] in the pixels of the user's photo ``rel`` (a path in the scene
    folder) -> ``(boxes, (width, height) of the image they are now in, its pixels per photo
    pixel)``. With the photo's own camera and the poses stage's camera of the view
    (``photo_cams[key]``, ``cams[key]``) the boxes are carried into the stages' copy of the
    photo under ``root`` (:func:`gdiff.sfm.undistort.boxes_to_pinhole`: lens distortion
    removed, resampled to the common camera); without them they stay in the photo's pixels,
    the size that of the user's photo (under ``original``, else ``root``). A box that leaves
    the stages' image (a margin the undistortion crops) is dropped, logged."""
    cam, photo = cams.get(key), photo_cams.get(key)
    if cam is None or photo is None:
        src = original / rel if original is not None else None
        return boxes, _image_size(src if src is not None and src.is_file() else root / rel), 1.0
    out = boxes_to_pinhole(boxes, photo, cam)
    keep = (out[:, 2] > out[:, 0]) & (out[:, 3] > out[:, 1])
    if not keep.all():
        log.warning("%s: %d box(es) lie outside the undistorted / resampled image (a margin "
                    "the poses stage cropped); not scored", name, int((~keep).sum()))
    return out[keep], (cam.width, cam.height), float(np.sqrt(cam.fx * cam.fy /
                                                            (photo.fx * photo.fy)))


def box_image(root: Path, key: str, eval_stems) -> tuple[str, str | Path] | None:
    """Where an entry ``key`` of ``eval/boxes.json`` points (module docstring): ``("view",
    stem)`` for an eval view (a bare name whose stem is in ``eval_stems``), ``("train", rel)``
    for an image of the scene folder ``root`` (``rel`` its path there; a bare file name taken
    from ``after/``, else ``before/``), None when neither exists."""
    if "/" not in key and Path(key).stem in eval_stems:
        return "view", Path(key).stem
    if "/" in key:
        rel = Path(key)
    else:
        rel = next((Path(d) / key for d in ("after", "before") if (root / d / key).is_file()),
                   Path("after") / key)
    return ("train", rel) if (root / rel).is_file() else None


def check_boxes(boxes_json: Path, root: Path, eval_stems) -> None:
    """Check ``eval/boxes.json`` of the scene folder ``root`` before anything runs: every
    entry with boxes names an eval view or an image of the scene (:func:`box_image`);
    :class:`SceneError` naming the entry otherwise. An entry without boxes may name an image
    the scene does not have (a view left out of a dataset's file): nothing to score there."""
    for key, boxes in read_boxes(boxes_json).items():
        if len(boxes) and box_image(root, key, eval_stems) is None:
            raise SceneError(f"{boxes_json}: entry {key!r} has {len(boxes)} box(es) but is "
                             f"neither an eval view nor an image of the scene ({root / key} "
                             "and after/, before/ hold no such image); fix the name or remove "
                             "the entry")


def _attach_boxes(root: Path, views: list[EvalView], box_gt: dict[str, np.ndarray],
                  cams: dict, have_cameras: bool, original: Path | None = None,
                  photo_cams: dict | None = None, source: Path | None = None
                  ) -> list[EvalView]:
    """Give eval views their boxes; return the box views of training images (module
    docstring). The boxes are in the pixels of the user's photos (``original``: their scene
    folder when ``root`` is the poses stage's copy); ``photo_cams`` (by view, as ``cams``) the
    photos' own cameras, with which they are carried into the copy (:func:`_boxes_in_image`).
    ``source``: the ``boxes.json`` read, named in messages."""
    photo_cams = photo_cams or {}
    source = source or root / "eval" / "boxes.json"
    by_name = {v.name: v for v in views}
    extra = []
    for key, boxes in sorted(box_gt.items()):
        target = box_image(root, key, by_name)
        if target is None:
            if not len(boxes):
                log.info("%s: entry %r has no boxes and names no image of the scene: skipped",
                         source, key)
                continue
            raise SceneError(f"{source}: entry {key!r} is neither an eval view nor an image "
                             f"of the scene ({root / key} does not exist)")
        if target[0] == "view":
            v = by_name[target[1]]
            img = v.after or v.before
            view_key = ("eval_after" if v.after is not None else "eval_before", target[1])
            v.boxes, v.box_size, v.box_px = _boxes_in_image(
                boxes, key, root, img.relative_to(root), view_key, cams, photo_cams, original)
            continue
        rel = target[1]
        cam = cams.get(("train", rel.as_posix()))
        if cam is None and have_cameras:
            log.warning("%s: no camera for %s in cameras.json; its boxes are not scored",
                        source, rel)
        b, size, px = _boxes_in_image(boxes, key, root, rel, ("train", rel.as_posix()), cams,
                                      photo_cams, original)
        extra.append(EvalView(rel.with_suffix("").as_posix(), None, camera=cam, boxes=b,
                              box_size=size, box_px=px, image=root / rel))
    return extra


# ---------------------------------------------------------------------------------- methods


def build_methods(options: EvalOptions, pmodel: Any = None, render: Callable | None = None,
                  detect: Callable | None = None, depth: Callable | None = None,
                  evidence: str | Path | None = None, **idcompare_kwargs
                  ) -> dict[str, Callable]:
    """The methods named in ``options.methods``, ready for :func:`evaluate_scene`.

    ``pmodel``: the trained partition model (needed for ``partition``); ``evidence``: the
    compare stage's ``change/evidence3d.npz`` (``evidence3d`` needs it and ``depth``; without
    them it is skipped); ``render(camera, t)``:
    optional renderer standing in for missing eval images; ``depth(camera, t)``: optional depth
    renderer giving ``idcompare`` the model's depth (``options.idcompare_depth``); ``detect``: override of
    ``gdiff.compare.detect_changes_pair`` for ``idcompare``; ``idcompare_kwargs`` (e.g.
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
        elif name == "render_diff":
            if render is None:
                log.info("render_diff skipped: it needs the fitted model to render")
                continue
            out[name] = render_diff_method(render, options.pixel_blur_sigma,
                                           options.pixel_min_threshold)
        elif name == "evidence3d":
            if evidence is None or depth is None:
                log.info("evidence3d skipped: it needs the compare stage's evidence3d.npz and "
                         "the fitted model's depth")
                continue
            out[name] = evidence3d_method(evidence, depth)
        elif name == "partition":
            if pmodel is None:
                raise ConfigError("evaluate.methods lists 'partition' but no partition model "
                                  "was given")
            out[name] = partition_method(pmodel)
    return out


def model_renderer(model: Any, keep_mb: float = 256.0) -> Callable[[Camera, float], np.ndarray]:
    """``render(camera, t) -> rgb float32 [H, W, 3]`` (read-only) from a fitted 4D model
    (``gdiff.splat.render.render``, imported on first use).

    Renders are kept, up to ``keep_mb`` MB, and returned again for the same camera and time:
    the evaluate rule asks for each eval view twice (``render_diff``, then the fit's quality
    in :func:`render_quality`)."""
    kept: dict[tuple, np.ndarray] = {}
    budget = [keep_mb * 1e6]

    def render(camera: Camera, t: float) -> np.ndarray:
        import torch

        from .splat.render import render as splat_render  # lazy: stage module

        key = (camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy,
               np.asarray(camera.c2w, np.float64).tobytes(), float(t))
        if key in kept:
            return kept[key]
        with torch.no_grad():
            rgb = splat_render(model, [camera], t, render_mode="RGB")["rgb"]
        rgb = np.asarray(rgb.detach().cpu().numpy(), dtype=np.float32)
        rgb = np.clip(rgb[0] if rgb.ndim == 4 else rgb, 0.0, 1.0)
        rgb.setflags(write=False)
        if rgb.nbytes <= budget[0]:
            kept[key] = rgb
            budget[0] -= rgb.nbytes
        return rgb

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
                            device: str = "auto", evidence: str | Path | None = None,
                            keyframes: str | Path | None = None) -> pd.DataFrame:
    """The ``evaluate`` rule: load the partition model (whose fitted 4D model also renders any
    eval image a dataset lacks) and score every method of ``options.methods`` side by side.
    ``keyframes``: the compare stage's ``change/keyframes.csv``, for where it could judge the
    boxes of a training image (:func:`judged_maps`)."""
    from .options import from_config
    from .partition import load_partition_model  # lazy: stage module
    from .segment import SegmentOptions

    pmodel = load_partition_model(partition_model, device)
    seg = from_config(SegmentOptions, segment_options, "segment")
    render = model_renderer(pmodel.fit)
    methods = build_methods(options, pmodel=pmodel, render=render,
                            depth=model_depth(pmodel.fit), evidence=evidence,
                            segment_options=seg)
    df = evaluate_scene(scene_dir, cameras_json, out_dir, scene_name, methods, options,
                        judged=judged_maps(keyframes) if keyframes is not None else None)
    q = render_quality(find_eval_views(scene_dir, cameras_json), render)
    write_csv(Path(out_dir) / "fit_quality.csv", q)
    for t, g in q.groupby("time"):
        log.info("%s: fitted model at the eval views, t=%g: PSNR %.2f dB (mean of %d)",
                 scene_name, t, g["psnr"].mean(), len(g))
    return df


def render_quality(views: list[EvalView], render: Callable[[Camera, float], np.ndarray]
                   ) -> pd.DataFrame:
    """PSNR (dB, sRGB-encoded values in [0, 1]) of the fitted model rendered at every eval view
    with a camera, at t=0 against ``eval/before`` and at t=1 against ``eval/after`` (at the
    ground-truth mask's size): the fit's quality at novel views. Columns ``view, time, psnr``;
    written by the evaluate rule as ``eval/fit_quality.csv``."""
    rows = []
    for v in views:
        if v.mask is None or v.camera is None:
            continue
        cam = v.camera_at_gt_size()
        for t, path in ((0, v.before), (1, v.after)):
            if path is None:
                continue
            mse = float(np.mean((render(cam, float(t)) - v.read_image(t)) ** 2))
            rows.append({"view": v.name, "time": t,
                         "psnr": -10.0 * math.log10(max(mse, 1e-12))})
    return pd.DataFrame(rows, columns=["view", "time", "psnr"])


# ---------------------------------------------------------------------------------- scoring


def evaluate_scene(scene_dir: str | Path, cameras_json: str | Path | None, out_dir: str | Path,
                   scene_name: str, methods: dict[str, Callable], options: EvalOptions,
                   judged: dict[str, Path] | None = None) -> pd.DataFrame:
    """Score every method at every eval view; write the outputs listed in the module docstring.

    ``methods``: name -> ``f(view: EvalView) -> bool mask [H, W]`` (or ``(mask, prob)``,
    ``{"mask", "prob"}``, :class:`gdiff.baselines.Prediction`); a prediction of another size
    than the ground truth is resized (nearest) with a warning. ``judged`` (optional): box view
    name -> the compare stage's judged map at that training image (:func:`judged_maps`); with
    it each of the view's boxes gets the share of its core the compare stage could judge
    (``boxes.csv``, column ``judged``). Returns the metrics table.
    """
    out_dir = Path(out_dir)
    views = find_eval_views(image_root(scene_dir, cameras_json), cameras_json, scene_dir)
    rows, box_frames = [], []
    for view in progress(views, desc=f"evaluate {scene_name}"):
        gt = view.read_gt() if view.mask is not None else None
        h, w = view.shape()
        min_area = int(math.ceil(options.box_min_area * h * w))
        objects = object_regions(view.object_masks(), min_area) if gt is not None else []
        gt_boxes = view.boxes_at_scored_size()
        margin = options.box_margin * (view.box_px * w / view.box_size[0] if view.box_size
                                       else 1.0)
        box_judged = (_judged_share(judged[view.name], gt_boxes, (h, w), options)
                      if gt_boxes is not None and judged and view.name in judged else None)
        preds: dict[str, Prediction] = {}
        for name, fn in methods.items():
            if gt is None and name not in CAMERA_METHODS:
                log.info("%s: %s skipped at %s (box ground truth on a training image: the method "
                         "needs an eval photo pair)", scene_name, name, view.name)
                continue
            t0 = time.perf_counter()
            try:
                pred = as_prediction(fn(view))
            except MethodNotApplicable as e:
                log.info("%s: %s skipped (%s)", scene_name, name, e)
                continue
            seconds = time.perf_counter() - t0
            pred = _fit_to(pred, (h, w), f"{name} at view {view.name}")
            scores = {}
            if gt is not None:
                scores, boxes = score_view(pred.mask, gt, pred.prob, options.box_iou, min_area)
                scores.update(object_scores(pred.mask, objects, options.object_found_fraction))
                box_frames.append(boxes.assign(scene=scene_name, view=view.name, method=name))
            if gt_boxes is not None:
                scores.update(gt_box_scores(pred.mask, gt_boxes, options.box_core,
                                            options.object_found_fraction, margin))
                box_frames.append(_gt_box_rows(pred.mask, gt_boxes, options, box_judged).assign(
                    scene=scene_name, view=view.name, method=name))
            rows.append({"scene": scene_name, "view": view.name, "method": name, **scores,
                         "seconds": seconds})
            write_mask(out_dir / "maps" / name / f"{view.name}.png", pred.mask)
            preds[name] = pred
        if options.overlays and preds:
            truth = gt if gt is not None else _box_mask(gt_boxes, (h, w))
            write_image(out_dir / "overlays" / f"{view.name}.png",
                        overlay_panel(view.display_image(), preds, truth,
                                      options.overlay_max_side,
                                      [r for r in rows if r["view"] == view.name]))
    df = pd.DataFrame(rows, columns=METRIC_COLUMNS)
    box_cols = ["scene", "view", "method", "kind", "x0", "y0", "x1", "y1", "score", "matched",
                "iou", "core", "judged"]
    frames = [f for f in box_frames if len(f)]
    boxes = (pd.concat(frames, ignore_index=True).reindex(columns=box_cols) if frames
             else pd.DataFrame(columns=box_cols))
    write_csv(out_dir / "metrics.csv", df)
    write_csv(out_dir / "boxes.csv", boxes)
    write_csv(out_dir / "scene_summary.csv", aggregate(df, boxes) if len(df) else
              pd.DataFrame(columns=["scene", "method"]))
    for m, g in df.groupby("method"):
        log.info("%s %s: F1 %.3f IoU %.3f (mean of %d views)", scene_name, m,
                 g["F1"].mean(), g["IoU"].mean(), len(g))
        if g["gtbox_N"].notna().any():
            log.info("%s %s: %d of %d boxes found, %.3f of the image flagged far from any box",
                     scene_name, m, int(g["gtbox_found"].sum()), int(g["gtbox_N"].sum()),
                     g["far_FP"].sum() / max(g["far_N"].sum(), 1))
            gb = boxes[(boxes["kind"] == "gt_box") & (boxes["method"] == m)]
            gb = gb.assign(box=gb.groupby("view").cumcount())  # its place in boxes.json
            blind = gb[gb["matched"].eq(False) & (gb["judged"] < 0.5)]
            if len(blind):
                log.info("%s %s: %d of the missed boxes lie mostly where the compare stage "
                         "could not judge (no photo of one of the visits shows them; "
                         "boxes.csv, column judged): %s", scene_name, m, len(blind),
                         ", ".join(f"{v} box {b}" for v, b in zip(blind["view"], blind["box"])))
    return df


def judged_maps(keyframes_csv: str | Path) -> dict[str, Path]:
    """The compare stage's judged maps at the training images: ``{box view name (the image's
    path without extension, e.g. "after/v00"): map path}`` from ``change/keyframes.csv``
    (column ``judged``; :func:`gdiff.compare.coverage.judged_map`). Empty when the file has no
    such column or no map (a scene with photos of one time only)."""
    path = Path(keyframes_csv)
    kf = pd.read_csv(path)
    if "judged" not in kf:
        return {}
    root = path.parent.parent  # paths in keyframes.csv are relative to results/<scene>/
    return {str(Path(img).with_suffix("").as_posix()): root / j
            for img, j in zip(kf["image"], kf["judged"])
            if isinstance(img, str) and isinstance(j, str) and j}


def _judged_share(path: Path, boxes: np.ndarray, shape: tuple[int, int],
                  options: EvalOptions) -> np.ndarray:
    """float [K]: per box (xyxy pixels of a map of ``shape``), the share of its core that the
    judged map at ``path`` (resized, nearest) says the compare stage judged
    (>= :data:`gdiff.compare.coverage.JUDGED_SEEN`)."""
    from .compare.coverage import JUDGED_SEEN

    m = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if m is None:
        raise SceneError(f"{path}: judged map cannot be read (missing or corrupt); re-run "
                         "compare")
    h, w = shape
    if m.shape != (h, w):
        m = cv2.resize(m, (w, h), interpolation=cv2.INTER_NEAREST)
    b = np.asarray(boxes, np.float64).reshape(-1, 4)
    return gt_box_cores(m >= JUDGED_SEEN, b, options.box_core, options.object_found_fraction)[0]


def _gt_box_rows(pred: np.ndarray, boxes: np.ndarray, options: EvalOptions,
                 judged: np.ndarray | None = None) -> pd.DataFrame:
    """The rows of ``boxes.csv`` for the boxes of ``eval/boxes.json`` at one view and method:
    ``kind`` ``gt_box``, the box (xyxy pixels of the scored map), ``core`` the fraction of its
    core marked changed by ``pred`` [H, W], ``matched`` whether that makes it found
    (:func:`gdiff.metrics.gt_box_cores`) and ``judged`` (float [K] or empty: the share of its
    core the compare stage judged, :func:`_judged_share`); ``score`` and ``iou`` are empty."""
    b = np.asarray(boxes, np.float64).reshape(-1, 4)
    core, found = gt_box_cores(pred, b, options.box_core, options.object_found_fraction)
    return pd.DataFrame({"kind": "gt_box", "x0": b[:, 0], "y0": b[:, 1], "x1": b[:, 2],
                         "y1": b[:, 3], "score": np.nan, "matched": found, "iou": np.nan,
                         "core": core, "judged": np.nan if judged is None else judged})


def _box_mask(boxes: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Filled boxes as a bool [H, W] mask (the 'ground truth' panel of a box view's overlay)."""
    m = np.zeros(shape, bool)
    h, w = shape
    for x0, y0, x1, y1 in np.asarray(boxes).reshape(-1, 4):
        m[max(0, int(round(y0))):min(h, int(round(y1))),
          max(0, int(round(x0))):min(w, int(round(x1)))] = True
    return m


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
