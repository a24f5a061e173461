"""benchmarks/swap_visits.py: a scene with its visits exchanged (added objects become removed)."""

import importlib.util
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from gdiff.cameras import load_cameras
from gdiff.evaluate import read_boxes

_spec = importlib.util.spec_from_file_location(
    "swap_visits", Path(__file__).resolve().parents[1] / "benchmarks" / "swap_visits.py")
SV = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(SV)


def _texture(rng, h=240, w=320):
    """A photo-like texture (blobs and edges at several scales), uint8 [H, W, 3]."""
    img = np.zeros((h, w, 3), np.float32)
    for s in (3, 9, 27):
        n = cv2.resize(rng.random((h // s + 2, w // s + 2, 3)).astype(np.float32), (w, h),
                       interpolation=cv2.INTER_NEAREST if s == 3 else cv2.INTER_LINEAR)
        img += n / 3
    return (255 * img).astype(np.uint8)


def test_swap_visits_exchanges_sets_and_carries_boxes(tmp_path):
    """The waypoint's before photo is its after photo seen 18 px to the left and 6 px down:
    the boxes drawn on the after photo land on the before one shifted by that (within 2 px),
    the photos and cameras.json change sets and times, an empty entry stays empty."""
    rng = np.random.default_rng(0)
    scene = tmp_path / "scene"
    for s in ("before", "after", "eval"):
        (scene / s).mkdir(parents=True)
    frames = []
    for i, (dx, dy) in enumerate([(18, 6), (0, 0)]):
        after = _texture(rng)
        before = cv2.warpAffine(after, np.float32([[1, 0, dx], [0, 1, dy]]), (320, 240),
                                borderMode=cv2.BORDER_REFLECT)
        cv2.imwrite(str(scene / "after" / f"v0{i}.png"), after)
        cv2.imwrite(str(scene / "before" / f"v0{i}.png"), before)
        for s, t in (("before", 0), ("after", 1)):
            c2w = np.eye(4)
            c2w[0, 3] = i + 0.01 * t
            frames.append({"image": f"{s}/v0{i}.png", "set": s, "time": t, "c2w": c2w.tolist()})
    (scene / "cameras.json").write_text(json.dumps(
        {"width": 320, "height": 240, "fx": 300.0, "fy": 300.0, "cx": 160.0, "cy": 120.0,
         "distortion": [0.01, 0, 0, 0], "frames": frames}))
    (scene / "eval" / "boxes.json").write_text(json.dumps(
        {"views": {"v00.png": {"boxes_xyxy_px": [[100, 80, 160, 150]]},
                   "v01.png": {"boxes_xyxy_px": []}}}))

    info = SV.swap_visits(scene, tmp_path / "swapped")
    out = tmp_path / "swapped"
    assert info["photos"] == 4 and info["boxes_carried"] == ["after/v00.png"]
    assert (out / "after" / "v00.png").resolve() == (scene / "before" / "v00.png").resolve()
    assert (out / "before" / "v01.png").resolve() == (scene / "after" / "v01.png").resolve()
    cams = {c.image: c for c in load_cameras(out / "cameras.json")}
    assert cams["after/v00.png"].time == 1 and cams["after/v00.png"].set == "after"
    assert cams["after/v00.png"].c2w[0, 3] == pytest.approx(0.0)  # the old before's pose
    assert cams["before/v00.png"].c2w[0, 3] == pytest.approx(0.01)
    assert json.loads((out / "cameras.json").read_text())["distortion"][0] == 0.01
    boxes = read_boxes(out / "eval" / "boxes.json")
    np.testing.assert_allclose(boxes["after/v00.png"][0], [118, 86, 178, 156], atol=2.0)
    assert len(boxes["after/v01.png"]) == 0

    with pytest.raises(SystemExit, match="exists"):
        SV.swap_visits(scene, out)
    with pytest.raises(SystemExit, match="before/"):
        SV.swap_visits(tmp_path / "nothing", tmp_path / "x")
    (scene / "eval" / "boxes.json").write_text('{"v00.png": [[5, 5, 1, 1]]}')
    with pytest.raises(SystemExit, match="boxes.json"):
        SV.swap_visits(scene, tmp_path / "bad")
    # nothing half-written
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene", "swapped"]


def test_carry_boxes_without_a_homography():
    """Two images with nothing in common (flat grey and noise): no boxes are carried."""
    flat = np.full((120, 160), 128, np.uint8)
    noise = (np.random.default_rng(1).random((120, 160)) * 255).astype(np.uint8)
    assert SV.carry_boxes(np.array([[10.0, 10, 50, 50]]), flat, noise) is None
