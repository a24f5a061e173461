"""Video input (gdiff.video): frames picked by sharpness and spacing, used like photos.

The videos are made here from a synthetic orbit: the ``tiny`` scene's photos in capture order,
each written twice, once blurred (motion blur), so that the sharpest frame of each stretch is
the photo itself.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from gdiff.cameras import load_cameras
from gdiff.errors import SceneError
from gdiff.io import read_json
from gdiff.scene import discover_scenes, manifest_image_root, validate_scene, write_manifest
from gdiff.sfm import PosesOptions, run_poses
from gdiff.video import InputOptions, extract_frames, find_video, pick_frames, sharpness


def _write_video(path: Path, photos: list[Path]) -> None:
    """Each photo as a blurred then a sharp frame (MJPEG, nearly lossless)."""
    first = cv2.imread(str(photos[0]))
    h, w = first.shape[:2]
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (w, h))
    assert out.isOpened()
    kernel = np.full((1, 9), 1 / 9)
    for p in photos:
        img = cv2.imread(str(p))
        out.write(cv2.filter2D(img, -1, kernel))
        out.write(img)
    out.release()


@pytest.fixture(scope="module")
def video_scene(synth_tiny_dir, tmp_path_factory):
    """The tiny scene with before/ and after/ replaced by before.avi and after/clip.avi."""
    src = Path(synth_tiny_dir)
    dst = tmp_path_factory.mktemp("video") / "tiny_video"
    dst.mkdir()
    shutil.copytree(src / "eval", dst / "eval")
    _write_video(dst / "before.avi", sorted((src / "before").glob("*.png")))
    (dst / "after").mkdir()
    _write_video(dst / "after" / "clip.avi", sorted((src / "after").glob("*.png")))
    return dst


def test_pick_frames_takes_the_sharpest_of_each_stretch():
    scores = np.array([1, 5, 2, 9, 3, 3, 8, 1, 0, 4.0])
    assert pick_frames(scores, 3) == [1, 3, 9]  # stretches 0-2, 3-6, 7-9
    assert pick_frames(scores, 20) == list(range(10))
    sharp = np.kron(np.indices((32, 32)).sum(0) % 2, np.ones((2, 2))).astype(np.uint8) * 255
    frame = np.repeat(sharp[..., None], 3, -1)
    assert sharpness(frame) > 10 * sharpness(cv2.GaussianBlur(frame, (9, 9), 3))


def test_extract_frames_keeps_the_sharp_photos(video_scene, synth_tiny_dir, tmp_path):
    names = extract_frames(video_scene / "before.avi", tmp_path, 10)
    # 20 frames (blurred, sharp per photo), 10 stretches of 2: the sharp frame of each pair
    assert names == [f"frame_{2 * i + 1:06d}.png" for i in range(10)]
    photos = sorted((Path(synth_tiny_dir) / "before").glob("*.png"))
    for name, photo in zip(names, photos):
        frame = cv2.imread(str(tmp_path / name))
        err = np.abs(frame.astype(float) - cv2.imread(str(photo))).mean() / 255
        assert err < 0.06  # that photo, with MJPEG's loss
        blurred = cv2.filter2D(cv2.imread(str(photo)), -1, np.full((1, 9), 1 / 9))
        assert sharpness(frame) > 1.5 * sharpness(blurred)
    with pytest.raises(SceneError, match="cannot be opened as a video"):
        bad = tmp_path / "bad.mp4"
        bad.write_bytes(b"not a video")
        extract_frames(bad, tmp_path / "x", 5)


def test_scene_with_videos_is_found_and_validated(video_scene):
    assert list(discover_scenes(video_scene)) == ["tiny_video"]
    assert find_video(video_scene, "before") == video_scene / "before.avi"
    assert find_video(video_scene, "after") == video_scene / "after" / "clip.avi"
    m = validate_scene(video_scene)
    vids = [r for r in m["images"] if r.get("video")]
    assert [(r["path"], r["set"], r["frames"]) for r in vids] == [
        ("before.avi", "before", 20), ("after/clip.avi", "after", 20)]
    assert (m["width"], m["height"]) == (128, 96)


def test_video_beside_photos_is_an_error(video_scene, tmp_path):
    scene = tmp_path / "mixed"
    shutil.copytree(video_scene, scene)
    shutil.copy(scene / "eval" / "before" / "000.png", scene / "after" / "000.png")
    with pytest.raises(SceneError, match="both a video"):
        validate_scene(scene)


def test_manifest_frames_then_poses_register_them(video_scene, tmp_path):
    manifest = write_manifest(video_scene, tmp_path / "input" / "manifest.json",
                              InputOptions(video_frames=10))
    root = manifest_image_root(tmp_path / "input" / "manifest.json", video_scene)
    assert root == tmp_path / "input" / "images"
    sets = [r["set"] for r in manifest["images"] if r["set"] in ("before", "after")]
    assert sets.count("before") == 10 and sets.count("after") == 10
    for r in manifest["images"]:  # frames, photos and masks all in the one folder
        assert (root / r["path"]).is_file()
    assert read_json(tmp_path / "input" / "manifest.json")["image_root"] == "images"
    images = [(r["path"], r["set"]) for r in manifest["images"] if r["set"] != "eval_mask"]
    out = tmp_path / "poses"
    summary = run_poses(video_scene, out, PosesOptions(num_threads=2), images=images,
                        image_root=root)
    assert summary["registered"] == summary["images"]
    cams = load_cameras(out / "cameras.json")
    assert {c.image for c in cams} == {n for n, _ in images}
    assert read_json(out / "cameras.json")["image_dir"] == "../input/images"
    from gdiff.cameras import image_root

    assert image_root(video_scene, out / "cameras.json").resolve() == root.resolve()
