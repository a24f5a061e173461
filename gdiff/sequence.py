"""Render stage: both interpolated paths at t=0 and t=1 -> EXR frames, previews, contact sheets.

Four sequences are rendered with the fitted 4D model (:mod:`gdiff.splat`): P~1 (the path
through the before poses) at t=0 and t=1, and P~2 (the after poses) at t=0 and t=1. Files in
``out_dir`` (``results/<scene>/render/``)::

    <path>/<t0|t1>/NNNNN.exr     R, G, B (linear, half), A (alpha, half), Z (depth, float32);
                                 see gdiff.exr; compression ``compression``. The header holds
                                 worldToCamera (OpenCV w2c), gdiff_path, gdiff_time,
                                 gdiff_frame.
    <path>/<t0|t1>/NNNNN.png     sRGB preview (8 bit), only with ``previews`` (nothing
                                 downstream reads them; the contact sheets are always written)
    <path>/<t0|t1>_sheet.png     contact sheet (key frames framed in green, frame numbers)
    frames.json                  the index, written last (see :func:`render_sequences`)

Frames are rendered at the intrinsics of ``sequence/poses.json`` (the photos' size); with
``max_side`` > 0 the cameras are scaled down so the longest side is at most ``max_side``, and
``frames.json`` then records the scaled intrinsics and the ``scale``.

Frames are written (EXR compression, PNG previews) on one background thread while the next
batch is rasterised; OpenEXR and OpenCV release the GIL while they compress. Every frame is
written before ``frames.json``; a failed write stops the stage with that error.
"""

from __future__ import annotations

import logging
import math
import os
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .cameras import Camera, image_root
from .errors import SceneError
from .exr import FRAME_COMPRESSIONS, write_frame
from .interpolate import load_sequence
from .io import read_image_sized, write_image, write_json
from .log import progress

log = logging.getLogger("gdiff.sequence")

TIMES = {"t0": 0.0, "t1": 1.0}
KEY_SET = {"p1": ("t0", "before"), "p2": ("t1", "after")}  # path -> time of its source photos


@dataclass
class RenderOptions:
    """Options of the render stage (config section ``render``).

    Attributes:
        max_side: longest side of the rendered frames in pixels; 0 = the size in
            ``sequence/poses.json`` (the photos' size).
        batch: frames rasterised per renderer call (bounds memory).
        background: ``auto`` (the fit's training background; black if it trained on random
            backgrounds), ``black`` or ``white``.
        compression: OpenEXR compression of the frames (:data:`gdiff.exr.FRAME_COMPRESSIONS`):
            ``zip``, ``zips``, ``piz``, ``rle``, ``none`` (lossless), or ``dwaa`` / ``dwab``
            (lossy on the colour channels only; alpha and depth stay exact).
        dwa_level: OpenEXR ``dwaCompressionLevel`` for ``dwaa`` / ``dwab`` (higher = smaller
            files, coarser colour; OpenEXR's default is 45).
        previews: also write an 8-bit PNG preview per frame (for inspection only).
        keep_frames: keep the frame folders after segment and compare have read them (the
            workflow otherwise marks them temporary; read by the Snakefile, not by this stage).
        sheet_max_frames: frames shown on a contact sheet (evenly spaced; key frames kept
            first when thinning).
        sheet_columns: thumbnails per row of a contact sheet.
        sheet_thumb_side: longest side of a contact-sheet thumbnail in pixels.
    """

    max_side: int = 0
    batch: int = 8
    background: str = "auto"
    compression: str = "dwaa"
    dwa_level: float = 45.0
    previews: bool = False
    keep_frames: bool = False
    sheet_max_frames: int = 48
    sheet_columns: int = 8
    sheet_thumb_side: int = 160

    def __post_init__(self):
        if self.max_side < 0:
            raise ValueError("max_side must be >= 0 (0 = size of the poses)")
        if self.batch < 1:
            raise ValueError("batch must be >= 1")
        if self.background not in ("auto", "black", "white"):
            raise ValueError(f"background must be auto, black or white, not {self.background!r}")
        if self.compression not in FRAME_COMPRESSIONS:
            raise ValueError(f"compression must be one of {', '.join(FRAME_COMPRESSIONS)}, "
                             f"not {self.compression!r}")
        if not self.dwa_level > 0:
            raise ValueError("dwa_level must be > 0")
        if self.sheet_max_frames < 1 or self.sheet_columns < 1 or self.sheet_thumb_side < 8:
            raise ValueError("sheet_max_frames and sheet_columns must be >= 1, "
                             "sheet_thumb_side >= 8")


def _background(model, option: str) -> list[float]:
    if option == "auto":
        trained = (getattr(model, "meta", None) or {}).get("options", {}).get("background")
        option = "white" if trained == "white" else "black"
    return [1.0, 1.0, 1.0] if option == "white" else [0.0, 0.0, 0.0]


def _scale_cameras(cams: list[Camera], max_side: int) -> tuple[list[Camera], float]:
    if not cams or not max_side:
        return cams, 1.0
    side = max(cams[0].width, cams[0].height)
    if side <= max_side:
        return cams, 1.0
    f = max_side / side
    return [c.scaled(f) for c in cams], f


def sheet_indices(keys: list[bool], max_frames: int) -> list[int]:
    """Frame indices shown on a contact sheet: all frames if they fit; otherwise key frames
    first (evenly thinned if even they do not fit), then evenly spaced other frames."""
    n = len(keys)
    if n <= max_frames:
        return list(range(n))
    key_idx = [i for i, k in enumerate(keys) if k]
    if len(key_idx) >= max_frames:
        pick = np.linspace(0, len(key_idx) - 1, max_frames).round().astype(int)
        return sorted({key_idx[i] for i in pick})
    others = [i for i, k in enumerate(keys) if not k]
    m = max_frames - len(key_idx)
    pick = np.linspace(0, len(others) - 1, m).round().astype(int) if m > 0 else []
    return sorted(set(key_idx) | {others[i] for i in pick})


def contact_sheet(thumbs: list[np.ndarray], labels: list[str], keys: list[bool],
                  columns: int) -> np.ndarray:
    """Grid of thumbnails (float [h, w, 3] sRGB in [0, 1], one size) with a label under each;
    key frames get a green frame. Returns uint8 RGB [H, W, 3]."""
    h, w = thumbs[0].shape[:2]
    pad, bar = 4, 14
    cols = min(columns, len(thumbs))
    rows = math.ceil(len(thumbs) / cols)
    sheet = np.full((rows * (h + bar + pad) + pad, cols * (w + pad) + pad, 3), 38, np.uint8)
    green, grey = (30, 230, 50), (230, 230, 230)
    for k, (im, lab, key) in enumerate(zip(thumbs, labels, keys)):
        r, c = divmod(k, cols)
        y, x = pad + r * (h + bar + pad), pad + c * (w + pad)
        sheet[y:y + h, x:x + w] = (np.clip(im, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
        if key:
            cv2.rectangle(sheet, (x, y), (x + w - 1, y + h - 1), green, 2)
        cv2.putText(sheet, lab, (x + 2, y + h + bar - 3), cv2.FONT_HERSHEY_SIMPLEX, 0.35,
                    green if key else grey, 1, cv2.LINE_AA)
    return sheet


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB of two images in [0, 1] (same shape)."""
    mse = float(np.mean((np.clip(a, 0, 1) - np.clip(b, 0, 1)) ** 2))
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


class FrameWriter:
    """Runs file writes on one background thread, at most ``max_pending`` queued at once (so
    the rendered batches waiting to be written stay few). ``submit(fn, *args)`` queues
    ``fn(*args)``. Use as a context manager: a clean exit waits for every write and raises the
    first error; an exit on an exception waits for the queued writes and discards their errors
    (the first one is already propagating)."""

    def __init__(self, max_pending: int = 32):
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="gdiff-write")
        self._pending: deque[Future] = deque()
        self._max = max(1, int(max_pending))

    def submit(self, fn, *args, **kwargs) -> None:
        while len(self._pending) >= self._max:
            self._pending.popleft().result()
        self._pending.append(self._pool.submit(fn, *args, **kwargs))

    def __enter__(self) -> "FrameWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            while exc_type is None and self._pending:
                self._pending.popleft().result()
        finally:
            self._pool.shutdown(wait=True)


def render_sequences(model_path: str | os.PathLike, poses_json: str | os.PathLike,
                     out_dir: str | os.PathLike, options: RenderOptions | None = None,
                     device="auto", scene_dir: str | os.PathLike | None = None) -> dict:
    """Render P~1 and P~2 at t=0 and t=1 into ``out_dir`` (see module docstring).

    Args:
        model_path: ``fit/model.pt``.
        poses_json: ``sequence/poses.json``.
        out_dir: ``render/``; stale frames in the sequence folders are removed first.
        options: :class:`RenderOptions`.
        device: torch device spec (auto | cpu | cuda) or a ``torch.device``.
        scene_dir: if given, each key frame rendered at its photo's time (p1 at t0 against
            the before photo, p2 at t1 against the after photo) is compared with that photo
            (resized to the frame size) and the PSNR is reported.

    ``frames.json`` (written last)::

        {"width", "height", "fx", "fy", "cx", "cy",      # intrinsics of the rendered frames
         "scale": s,                                     # frame size / poses.json size
         "model", "poses", "background": [r, g, b],
         "paths": {"p1": {"set": "before",
                          "frames": [{"index": 0, "key": true, "image": "before/000.png",
                                      "c2w": 4x4}, ...],
                          "t0": {"time": 0.0, "exr": ["p1/t0/00000.exr", ...],
                                 "png": ["p1/t0/00000.png", ...], "sheet": "p1/t0_sheet.png"},
                          "t1": {...}},
                   "p2": {...}},
         "key_psnr": {"p1": {"before/000.png": dB, ...}, "p2": {...}}}   # with scene_dir

    File paths are relative to ``out_dir``.

    Returns:
        Summary: frames per path, seconds, mean key-frame PSNR per path (with scene_dir).
    """
    import time

    import torch

    from .device import resolve_device
    from .splat.model import load_model
    from .splat.render import render

    opts = options or RenderOptions()
    out = Path(out_dir)
    dev = resolve_device(device)
    t_start = time.time()
    seq = load_sequence(poses_json)
    photo_root = image_root(scene_dir, poses_json)  # undistorted photos, if any
    for p in ("p1", "p2"):
        if not seq.get(p):
            raise SceneError(f"{poses_json}: path {p} is missing or empty; re-run the "
                             "interpolate stage")
    model = load_model(model_path, dev)
    bg = _background(model, opts.background)
    cams, scale = {}, 1.0
    for p, cl in seq.items():
        cams[p], scale = _scale_cameras(cl, opts.max_side)
    ref = cams["p1"][0]
    index = {"width": ref.width, "height": ref.height, "fx": ref.fx, "fy": ref.fy,
             "cx": ref.cx, "cy": ref.cy, "scale": scale, "model": str(model_path),
             "poses": str(poses_json), "background": bg, "paths": {}}
    total = sum(len(c) for c in cams.values()) * len(TIMES)
    log.info("rendering %d frames (%s) at %dx%d on %s", total,
             ", ".join(f"{p}: {len(c)} x 2 times" for p, c in cams.items()), ref.width,
             ref.height, dev)
    key_psnr: dict[str, dict[str, float]] = {}
    keys = {p: [c.image is not None for c in cl] for p, cl in cams.items()}
    for p, cl in cams.items():
        index["paths"][p] = {"set": cl[0].set, "frames": [
            {"index": i, "key": k, "image": c.image if k else None, "c2w": c.c2w.tolist()}
            for i, (c, k) in enumerate(zip(cl, keys[p]))]}
    seconds = {"model": 0.0, "raster": 0.0, "write": 0.0}
    bar = progress(total=total, desc="render", unit="frame")
    try:
        with FrameWriter() as writer:
            for tn, t in TIMES.items():
                tic = time.perf_counter()
                with torch.no_grad():
                    g = model.at_time(t)  # once per time, shared by both paths
                seconds["model"] += time.perf_counter() - tic
                for p, cl in cams.items():
                    show = set(sheet_indices(keys[p], opts.sheet_max_frames))
                    folder = out / p / tn
                    folder.mkdir(parents=True, exist_ok=True)
                    for stale in list(folder.glob("*.exr")) + list(folder.glob("*.png")):
                        stale.unlink()
                    thumbs, labels, tkeys = [], [], []
                    exr_files, png_files = [], []
                    for s in range(0, len(cl), opts.batch):
                        chunk = cl[s:s + opts.batch]
                        tic = time.perf_counter()
                        with torch.no_grad():
                            r = render(model, chunk, t, background=bg, render_mode="RGB+ED",
                                       gaussians=g, chunk=opts.batch)
                        rgb = r["rgb"].clamp_min(0).cpu().numpy()
                        alpha = r["alpha"].cpu().numpy()
                        depth = r["depth"].cpu().numpy()
                        seconds["raster"] += time.perf_counter() - tic
                        tic = time.perf_counter()
                        for j, cam in enumerate(chunk):
                            i = s + j
                            name = f"{i:05d}"
                            attrs = {"worldToCamera": cam.w2c.astype(np.float32),
                                     "gdiff_path": p, "gdiff_time": float(t), "gdiff_frame": i}
                            writer.submit(write_frame, folder / f"{name}.exr", rgb[j], alpha[j],
                                          depth[j], attributes=attrs, compression=opts.compression,
                                          dwa_level=opts.dwa_level)
                            exr_files.append(f"{p}/{tn}/{name}.exr")
                            preview = np.clip(rgb[j], 0.0, 1.0)
                            if opts.previews:
                                writer.submit(write_image, folder / f"{name}.png", preview)
                                png_files.append(f"{p}/{tn}/{name}.png")
                            if i in show:
                                thumbs.append(_thumb(preview, opts.sheet_thumb_side))
                                labels.append(f"{i}" + (f" {Path(cam.image).stem}"
                                                        if cam.image else ""))
                                tkeys.append(keys[p][i])
                            if scene_dir is not None and keys[p][i] and KEY_SET[p][0] == tn:
                                photo = read_image_sized(photo_root / cam.image,
                                                         preview.shape[1], preview.shape[0])
                                key_psnr.setdefault(p, {})[cam.image] = psnr(preview, photo)
                        seconds["write"] += time.perf_counter() - tic
                        bar.update(len(chunk))
                    sheet = out / p / f"{tn}_sheet.png"
                    write_image(sheet, contact_sheet(thumbs, labels, tkeys, opts.sheet_columns))
                    index["paths"][p][tn] = {"time": t, "exr": exr_files, "png": png_files,
                                             "sheet": f"{p}/{tn}_sheet.png"}
    finally:
        bar.close()
    summary = {"frames": {p: len(c) for p, c in cams.items()},
               "width": ref.width, "height": ref.height,
               "seconds": round(time.time() - t_start, 2),
               **{f"seconds_{k}": round(v, 2) for k, v in seconds.items()}}
    if key_psnr:
        index["key_psnr"] = key_psnr
        for p, d in key_psnr.items():
            summary[f"key_psnr_{p}"] = float(np.mean(list(d.values())))
            log.info("key frames of %s vs their photos: mean PSNR %.2f dB (min %.2f, %d frames)",
                     p, summary[f"key_psnr_{p}"], min(d.values()), len(d))
    write_json(out / "frames.json", index)
    log.info("render done: %s", summary)
    return summary


def _thumb(img: np.ndarray, side: int) -> np.ndarray:
    h, w = img.shape[:2]
    f = side / max(h, w)
    if f >= 1:
        return img.astype(np.float32)
    return cv2.resize(img, (max(1, round(w * f)), max(1, round(h * f))),
                      interpolation=cv2.INTER_AREA).astype(np.float32)


def load_render_index(frames_json: str | os.PathLike) -> dict:
    """Read ``render/frames.json`` and return it with absolute file paths.

    Returns the index dict where every ``exr``/``png``/``sheet`` entry is a :class:`Path`
    under the folder of ``frames_json``, and each path entry gains ``cameras``: the rendered
    :class:`Camera` per frame (intrinsics of the frames, ``image`` set on key frames).
    """
    from .io import read_json

    frames_json = Path(frames_json)
    data = read_json(frames_json)
    root = frames_json.parent
    try:
        for p, entry in data["paths"].items():
            for tn in TIMES:
                if tn in entry:
                    e = entry[tn]
                    e["exr"] = [root / f for f in e["exr"]]
                    e["png"] = [root / f for f in e.get("png", [])]
                    e["sheet"] = root / e["sheet"]
            entry["cameras"] = [
                Camera(data["width"], data["height"], data["fx"], data["fy"], data["cx"],
                       data["cy"], np.asarray(fr["c2w"]), image=fr.get("image"),
                       set=entry.get("set"), time=0 if entry.get("set") == "before" else 1)
                for fr in entry["frames"]]
    except (KeyError, TypeError) as e:
        raise SceneError(f"{frames_json}: malformed render index ({e}); re-run the render "
                         "stage") from None
    return data
