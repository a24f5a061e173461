"""Video input: a video per set instead of photos, turned into photos by the manifest stage.

A scene folder may hold ``before.mp4`` / ``after.mp4`` (any of :data:`VIDEO_EXTENSIONS`) or
exactly one video inside ``before/`` / ``after/`` instead of photos. The manifest stage picks
``input.video_frames`` frames of each video (:func:`pick_frames`: the video is cut into that
many stretches of equal length and the sharpest frame of each is kept, so the frames are
spread over the whole capture and blurred ones are avoided), writes them as PNG files under
``results/<scene>/input/images/<set>/`` (:func:`extract_frames`) and lists them in the
manifest like photos; every later stage uses them as photos (see :mod:`gdiff.scene`).

Sharpness is the variance of the Laplacian of the grey frame, measured at a longer side of at
most ``SHARPNESS_SIDE`` pixels (motion blur and defocus lower it).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .errors import SceneError
from .io import IMAGE_EXTENSIONS, write_image
from .log import progress

log = logging.getLogger("gdiff.video")

VIDEO_EXTENSIONS = (".mp4", ".mov", ".avi", ".mkv", ".m4v", ".webm")
SHARPNESS_SIDE = 320


@dataclass
class InputOptions:
    """Options of the input (manifest) stage (config section ``input``)."""

    video_frames: int = 40  # frames taken from each video (before / after)

    def __post_init__(self):
        if self.video_frames < 3:
            raise ValueError(f"video_frames must be >= 3, got {self.video_frames}")


def is_video(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in VIDEO_EXTENSIONS \
        and not path.name.startswith(".")


def find_video(root: str | Path, set_name: str) -> Path | None:
    """The video of set ``set_name`` (``before`` / ``after``) of scene folder ``root``, or None.

    ``root/<set>.<ext>`` or the only video inside ``root/<set>/``. Raises :class:`SceneError`
    when the choice is ambiguous (several videos, or a video beside photos).
    """
    root = Path(root)
    found = [p for p in sorted(root.glob(f"{set_name}.*")) if is_video(p)]
    folder = root / set_name
    photos = []
    if folder.is_dir():
        found += [p for p in sorted(folder.iterdir()) if is_video(p)]
        photos = [p for p in folder.iterdir()
                  if p.suffix in IMAGE_EXTENSIONS and not p.name.startswith(".")]
    if len(found) > 1:
        raise SceneError(f"{root}: several videos for '{set_name}' "
                         f"({', '.join(str(p.relative_to(root)) for p in found)}); keep one")
    if found and photos:
        raise SceneError(f"{root}: '{set_name}' has both a video ({found[0].relative_to(root)}) "
                         f"and photos in {set_name}/; keep one or the other")
    return found[0] if found else None


def _open(path: Path) -> cv2.VideoCapture:
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise SceneError(f"{path}: cannot be opened as a video (unknown codec or corrupt file); "
                         "convert it to H.264 MP4 or extract photos yourself")
    return cap


def video_info(path: str | Path) -> dict:
    """``{"width", "height", "frames"}`` of a video: the size of its first frame and the frame
    count its container states (the frames are counted exactly when they are extracted)."""
    path = Path(path)
    cap = _open(path)
    try:
        ok, frame = cap.read()
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    finally:
        cap.release()
    if not ok or frame is None:
        raise SceneError(f"{path}: the video has no readable frames")
    return {"width": int(frame.shape[1]), "height": int(frame.shape[0]), "frames": max(n, 1)}


def sharpness(frame: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image (``frame`` [H, W, 3] uint8 BGR)."""
    grey = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    s = SHARPNESS_SIDE / max(grey.shape)
    if s < 1:
        grey = cv2.resize(grey, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def pick_frames(scores: np.ndarray, count: int) -> list[int]:
    """Indices of the sharpest frame in each of ``count`` equal stretches of the video.

    ``scores`` [F] sharpness per frame. With fewer frames than ``count`` every frame is kept.
    """
    n = len(scores)
    if n <= count:
        return list(range(n))
    edges = np.linspace(0, n, count + 1).round().astype(int)
    return [int(a + np.argmax(scores[a:b])) for a, b in zip(edges[:-1], edges[1:])]


def extract_frames(video: str | Path, out_dir: str | Path, count: int) -> list[str]:
    """Pick ``count`` frames of ``video`` (see module docstring) and write them as
    ``out_dir/frame_NNNNNN.png`` (NNNNNN = frame number in the video), atomically; frames
    already there from an earlier run are replaced. Returns the file names in video order."""
    video, out_dir = Path(video), Path(out_dir)
    cap = _open(video)
    scores = []
    try:
        bar = progress(desc=f"sharpness {video.name}", unit="frame")
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            scores.append(sharpness(frame))
            bar.update(1)
        bar.close()
    finally:
        cap.release()
    if not scores:
        raise SceneError(f"{video}: the video has no readable frames")
    keep = set(pick_frames(np.asarray(scores), count))
    if len(keep) < 3:
        raise SceneError(f"{video}: only {len(keep)} frame(s); at least 3 are needed")
    out_dir.mkdir(parents=True, exist_ok=True)
    for old in out_dir.glob("frame_*.png"):
        old.unlink()
    names = []
    cap = _open(video)
    try:
        i = 0
        while len(names) < len(keep):
            ok, frame = cap.read()
            if not ok:
                raise SceneError(f"{video}: frame {i} could not be decoded on the second pass")
            if i in keep:
                name = f"frame_{i:06d}.png"
                write_image(out_dir / name, np.ascontiguousarray(frame[..., ::-1]))  # RGB uint8
                names.append(name)
            i += 1
    finally:
        cap.release()
    log.info("%s: %d frames, kept %d (sharpest of each of %d stretches)", video, len(scores),
             len(names), count)
    return names


__all__ = ["InputOptions", "VIDEO_EXTENSIONS", "extract_frames", "find_video", "is_video",
           "pick_frames", "sharpness", "video_info"]
