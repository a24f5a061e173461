"""Photos from different cameras between the sets (sizes, aspect ratios, focal lengths) and
EXIF-rotated photos: the manifest accepts them, the poses stage resamples every photo once to
one common pinhole camera (or writes upright copies), and later stages read them upright."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image, ImageOps

from gdiff.align import pose_errors
from gdiff.cameras import PHOTO_CAMERAS, Camera, cameras_to_json, image_root, load_cameras
from gdiff.errors import SceneError
from gdiff.evaluate import find_eval_views
from gdiff.io import exif_orientation, read_image, read_mask, write_image, write_mask
from gdiff.scene import validate_scene
from gdiff.segment.base import mask_bbox
from gdiff.sfm import PosesOptions, read_cameras_file, run_poses
from gdiff.sfm.images import _image_sizes
from gdiff.sfm.resample import common_camera, shares_one_camera, view_extent
from gdiff.splat.train import load_views

# ---------------------------------------------------------------------------------- helpers


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return -10.0 * math.log10(max(float(np.mean((a - b) ** 2)), 1e-12))


# PIL's transform for each EXIF orientation (what a viewer applies to the stored pixels)
_TRANSFORM = {2: Image.Transpose.FLIP_LEFT_RIGHT, 3: Image.Transpose.ROTATE_180,
              4: Image.Transpose.FLIP_TOP_BOTTOM, 5: Image.Transpose.TRANSPOSE,
              6: Image.Transpose.ROTATE_270, 7: Image.Transpose.TRANSVERSE,
              8: Image.Transpose.ROTATE_90}
_INVERSE = {1: 1, 2: 2, 3: 3, 4: 4, 5: 5, 6: 8, 7: 7, 8: 6}


def _save_with_orientation(path: Path, upright: np.ndarray, orientation: int) -> None:
    """Store the uint8 RGB image ``upright`` [H, W, 3] as pixels that show ``upright`` once
    EXIF ``orientation`` is applied (as a phone stores a portrait photo), with that tag."""
    im = Image.fromarray(upright)
    if orientation != 1:
        im = im.transpose(_TRANSFORM[_INVERSE[orientation]])
    exif = im.getexif()
    exif[0x0112] = orientation
    path.parent.mkdir(parents=True, exist_ok=True)
    im.save(path, exif=exif.tobytes(), **({"quality": 100} if path.suffix == ".jpg" else {}))


# ---------------------------------------------------------------------------------- manifest


def _img(path: Path, w: int, h: int, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), rng.integers(0, 255, (h, w, 3), dtype=np.uint8))


def _scene(root: Path, before=(48, 32), after=(40, 40), mask=None) -> Path:
    for i in range(3):
        _img(root / "before" / f"{i:03d}.png", *before, seed=i)
        _img(root / "after" / f"{i:03d}.png", *after, seed=10 + i)
    _img(root / "eval" / "before" / "000.png", *before)
    _img(root / "eval" / "after" / "000.png", *after)
    _img(root / "eval" / "masks" / "000.png", *(mask or after))
    return root


def test_manifest_accepts_sets_of_different_sizes(tmp_path):
    m = validate_scene(_scene(tmp_path / "s"))
    size = {r["path"]: (r["width"], r["height"]) for r in m["images"]}
    assert size["before/000.png"] == (48, 32) and size["after/002.png"] == (40, 40)
    assert size["eval/masks/000.png"] == (40, 40)
    assert m["sizes"] == [[48, 32], [40, 40]] and m["width"] is None and m["height"] is None


def test_manifest_eval_mask_must_have_an_eval_image_size(tmp_path):
    # the mask may have the size of the before image ...
    validate_scene(_scene(tmp_path / "a", mask=(48, 32)))
    # ... or of the after image, not another
    with pytest.raises(SceneError, match=r"masks/000.png: mask is 24x16 but eval/before/000.png "
                                         r"is 48x32, eval/after/000.png is 40x40"):
        validate_scene(_scene(tmp_path / "b", mask=(24, 16)))


# ------------------------------------------------------------------------------- EXIF tags


@pytest.mark.parametrize("orientation", range(1, 9))
def test_photos_are_read_upright(tmp_path, orientation):
    """Every reader (read_image, read_mask, manifest, the poses stage's sizes) applies the
    EXIF orientation: the stored pixels are the rotated/mirrored upright image."""
    rng = np.random.default_rng(orientation)
    upright = rng.integers(0, 255, (30, 50, 3), dtype=np.uint8)
    upright[:8, :12] = 255  # a marker at the top left
    path = tmp_path / "s" / "after" / "000.png"
    _save_with_orientation(path, upright, orientation)
    with Image.open(path) as im:
        stored = np.asarray(im)
        assert np.array_equal(np.asarray(ImageOps.exif_transpose(im)), upright)  # as a viewer
    assert exif_orientation(path) == orientation
    assert stored.shape[:2] == ((50, 30) if orientation >= 5 else (30, 50))
    assert np.array_equal(read_image(path), upright / np.float32(255))
    assert np.array_equal(read_mask(path), upright.max(axis=2) > 0)
    assert _image_sizes(path.parent, [path.name]) == {path.name: (50, 30)}
    for st in ("before", "after"):
        for i in range(3):
            if not (tmp_path / "s" / st / f"{i:03d}.png").exists():
                write_image(tmp_path / "s" / st / f"{i:03d}.png", upright)
    m = validate_scene(tmp_path / "s")
    assert all((r["width"], r["height"]) == (50, 30) for r in m["images"])


def test_jpeg_with_orientation_tag(tmp_path):
    upright = np.zeros((30, 50, 3), np.uint8)
    upright[:, 25:] = 200
    path = tmp_path / "p.jpg"
    _save_with_orientation(path, upright, 6)
    img = read_image(path)
    assert img.shape == (30, 50, 3) and np.abs(img * 255 - upright).mean() < 3


# ---------------------------------------------------------------- common camera (unit)


def test_common_camera_is_covered_by_every_photo():
    a = Camera(128, 96, 131.2, 131.2, 64.0, 48.0)
    b = Camera(112, 112, 150.0, 150.0, 54.0, 58.0)
    c = Camera(200, 100, 120.0, 121.0, 101.0, 49.0, dist=(-0.2, 0.05, 0.0, 0.0))
    covered = np.min([view_extent(k) for k in (a, b, c)], axis=0)
    common = common_camera([a, b, c])
    assert common.fx == common.fy == pytest.approx(150.0)  # the finest photo's density
    # inside every photo's view (all resampled pixels valid), and as large as whole pixels allow
    assert (view_extent(common) <= covered + 1e-9).all()
    assert np.allclose(view_extent(common), covered, atol=1 / 150)
    capped = common_camera([a, b, c], max_side=64)
    assert max(capped.width, capped.height) == 64
    assert (view_extent(capped) <= covered + 1e-9).all()
    assert not shares_one_camera([a, b]) and shares_one_camera([a, replace(a, image="x")])
    with pytest.raises(SceneError, match="principal point .* outside"):
        common_camera([a, Camera(64, 48, 50.0, 50.0, 70.0, 24.0, image="after/x.png")])


# --------------------------------------------------------------- poses stage: two cameras

# camera B of the after visit: square, longer focal length (principal point at the centre, as
# COLMAP assumes; off-centre ones are covered by test_common_camera_is_covered_by_every_photo)
CAM_B = dict(width=112, height=112, fx=150.0, fy=150.0, cx=56.0, cy=56.0)
# rays per pixel of the photos and of the direct renders: the tiny preset's 2 x 2 leaves its
# fine textures aliased, so that even a sub-pixel shift of a photo differs from a direct render
# by ~24.5 dB; at 3 x 3 the comparison measures the resampling (about 26 dB)
SUPERSAMPLE = 3


@pytest.fixture(scope="module")
def two_camera_scene(synth_tiny_scene, tmp_path_factory):
    """The tiny scene with the before photos (and eval/before) taken by the preset's 128x96
    camera and the after photos (and eval/after, eval masks) by camera B; known poses with
    per-frame intrinsics in cameras.json."""
    s = synth_tiny_scene
    root = tmp_path_factory.mktemp("two_cameras") / "scene"
    cams = s.cameras("before") + s.cameras("eval_before")
    cams += [replace(c, **CAM_B) for c in s.cameras("after") + s.cameras("eval_after")]
    for c in cams:
        out = s.render(c, "before" if c.time == 0 else "after", supersample=SUPERSAMPLE)
        write_image(root / c.image, out["rgb"])
        if c.set == "eval_after":
            write_mask(root / "eval" / "masks" / Path(c.image).name, out["changed"])
    (root / "cameras.json").write_text(json.dumps(cameras_to_json(cams)))
    return root, cams


@pytest.fixture(scope="module")
def two_camera_poses(two_camera_scene, tmp_path_factory):
    """The poses stage on :func:`two_camera_scene` with its known poses held: (summary, out)."""
    out = tmp_path_factory.mktemp("two_camera_poses") / "poses"
    return run_poses(two_camera_scene[0], out, PosesOptions(num_threads=1, refine_known=False)), out


def test_known_poses_of_two_cameras_are_resampled_to_one(two_camera_scene, two_camera_poses,
                                                         synth_tiny_scene):
    root, given = two_camera_scene
    summary, out = two_camera_poses
    assert summary["resampled"] and not summary["undistorted"]
    assert summary["image_dir"] == "images" and summary["num_points_triangulated"] > 100
    data = json.loads((out / "cameras.json").read_text())
    assert data["image_dir"] == "images"
    assert not any(k in fr for fr in data["frames"] for k in ("width", "fx", "cx"))
    cams = load_cameras(out / "cameras.json")
    common = cams[0]
    # the view both cameras cover (B's width, A's height) at camera B's (finer) density
    assert (common.width, common.height, common.fx) == (112, 109, pytest.approx(150.0))
    by_name = {c.image: c for c in given}
    photos = image_root(root, out / "cameras.json")
    psnr = {}
    for c in cams:
        assert np.allclose(c.c2w, by_name[c.image].c2w)
        img = read_image(photos / c.image)
        assert img.shape == (common.height, common.width, 3)
        want = synth_tiny_scene.render(c, "before" if c.time == 0 else "after",
                                       supersample=SUPERSAMPLE)["rgb"]
        psnr[c.image] = _psnr(img[3:-3, 3:-3], want[3:-3, 3:-3])
    # the resampled photos match photos taken directly with the common camera
    worst_before = min(v for k, v in psnr.items() if "before" in k)
    worst_after = min(v for k, v in psnr.items() if "after" in k)
    print(f"PSNR resampled vs direct render: before (128x96 -> 112x109) min "
          f"{worst_before:.1f} dB, after (112x112 -> 112x109) min {worst_after:.1f} dB; mean "
          f"{np.mean(list(psnr.values())):.1f} dB")
    assert worst_before > 25.0 and worst_after > 25.0, psnr
    # the eval masks (camera B's size) were resampled with their eval/after camera
    views = find_eval_views(photos, out / "cameras.json", root)
    assert len(views) == 3 and all(v.camera is not None for v in views)
    for v in views:
        gt = read_mask(v.mask)
        assert gt.shape == (common.height, common.width)
        direct = synth_tiny_scene.render(v.camera, "after")["changed"]
        assert np.mean(gt != direct) < 0.01
    # the sparse model and the fit see one camera
    import pycolmap

    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert {(k.width, k.height) for k in rec.cameras.values()} == {(112, 109)}
    views = load_views(photos, [c for c in cams if c.set in ("before", "after")], 0, "cpu")
    assert {tuple(v.image.shape) for v in views} == {(109, 112, 3)}


def test_boxes_on_the_photos_are_carried_into_the_resampled_images(
        two_camera_scene, two_camera_poses, synth_tiny_scene, tmp_path):
    """Box ground truth drawn on the user's photos (camera A's 128x96 before photos) lands on
    the same object in the resampled images (112x109 at camera B's focal length) the partition
    is scored on: the poses stage keeps the photos' own cameras (photo_cameras.json) and
    evaluate maps the boxes with them, its margin scaled by the zoom."""
    root, given = two_camera_scene
    _, out = two_camera_poses
    photo = load_cameras(out / PHOTO_CAMERAS)
    assert {c.image: (c.width, c.height, c.fx) for c in photo} == {
        c.image: (c.width, c.height, c.fx) for c in given}
    posed = {c.image: c for c in load_cameras(out / "cameras.json")}
    assert all(np.allclose(c.c2w, posed[c.image].c2w) for c in photo)
    # boxes of the changed object in three before photos, in camera A's pixels
    user = tmp_path / "user"
    want, drawn = {}, {}
    for c in [c for c in given if c.set == "before"]:
        box = _mask_box(synth_tiny_scene.render(c, "before")["changed"])
        direct = _mask_box(synth_tiny_scene.render(posed[c.image], "before")["changed"])
        if box is not None and direct is not None and len(want) < 3:
            drawn[c.image], want[Path(c.image).with_suffix("").as_posix()] = [box], direct
    assert len(want) == 3
    (user / "eval").mkdir(parents=True)
    (user / "eval" / "boxes.json").write_text(json.dumps(drawn))
    views = {v.name: v for v in find_eval_views(image_root(root, out / "cameras.json"),
                                                out / "cameras.json", user)}
    common = posed[next(iter(drawn))]
    for name, box in want.items():
        v = views[name]
        assert v.box_size == (common.width, common.height)
        assert v.box_px == pytest.approx(150.0 / given[0].fx)
        got = v.boxes_at_scored_size()[0]
        assert np.abs(got - box).max() < 1.5, (name, got, box)
        # the boxes as drawn would be off by several pixels there
        assert np.abs(np.asarray(drawn[name + ".png"][0]) - box).max() > 4.0


def _mask_box(mask: np.ndarray) -> list[float] | None:
    """``[x0, y0, x1, y1]`` (pixel edges) of a bool mask's pixels, None when it has fewer than
    20 or touches the border."""
    x0, y0, x1, y1 = mask_bbox(mask)
    if mask.sum() < 20 or min(x0, y0) == 0 or x1 == mask.shape[1] or y1 == mask.shape[0]:
        return None
    return [float(x0), float(y0), float(x1), float(y1)]


def test_colmap_registers_two_cameras_and_resamples(two_camera_scene, tmp_path):
    """Without known poses: one COLMAP camera per image size, then the same resampling; the
    sparse model is converted to the common camera."""
    import pycolmap

    root, given = two_camera_scene
    out = tmp_path / "poses"
    summary = run_poses(root, out, PosesOptions(num_threads=1, source="colmap"))
    assert summary["source"] == "colmap" and summary["resampled"]
    assert sum(summary["registered"].values()) == len(given)
    cams = load_cameras(out / "cameras.json")
    common = cams[0]
    assert shares_one_camera([replace(c, c2w=common.c2w, image=None, set=None, time=None)
                              for c in cams])
    # COLMAP's focal lengths (131.2 and 150 px) within 3 %: the common camera is camera B's
    assert common.fx == pytest.approx(150.0, rel=0.03)
    assert abs(common.width - 112) <= 3 and abs(common.height - 109) <= 4
    by_name = {c.image: c for c in given}
    err = pose_errors(cams, [by_name[c.image] for c in cams])
    assert err["rot_err_deg"].median() < 2.0 and err["center_err_frac"].median() < 0.05, err
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert {(k.width, k.height) for k in rec.cameras.values()} == {(common.width,
                                                                    common.height)}
    # keypoints were moved into the resampled photos: points reproject onto them
    rec.update_point_3d_errors()
    assert rec.compute_mean_reprojection_error() < 1.0
    assert read_image(out / "images" / cams[0].image).shape == (common.height, common.width, 3)


def test_resample_max_side_caps_the_common_camera(two_camera_scene, tmp_path):
    root, _ = two_camera_scene
    out = tmp_path / "poses"
    run_poses(root, out, PosesOptions(num_threads=1, resample_max_side=56),
              images=[(c.image, c.set) for c in two_camera_scene[1] if c.time == 0][:6]
              + [(c.image, c.set) for c in two_camera_scene[1] if c.time == 1][:6])
    cams = load_cameras(out / "cameras.json")
    assert (cams[0].width, cams[0].height) == (56, 54)
    assert read_image(out / "images" / cams[-1].image).shape == (54, 56, 3)


# ------------------------------------------------------------- poses stage: EXIF-rotated


def test_exif_rotated_photos_are_registered_upright(synth_tiny_dir, tmp_path):
    """Three before photos stored sideways/upside down with the matching EXIF tag: the poses
    stage gives COLMAP upright copies (it reads the stored pixels), and those are the photos
    every later stage reads (poses/images)."""
    src = Path(synth_tiny_dir)
    gt = [c for c in read_cameras_file(src / "gt_cameras.json") if c.set in ("before", "after")]
    root = tmp_path / "scene"
    tags = {"before/000.png": 6, "before/003.png": 8, "before/006.png": 3}
    for c in gt:
        rgb = cv2.cvtColor(cv2.imread(str(src / c.image)), cv2.COLOR_BGR2RGB)
        if c.image in tags:
            _save_with_orientation(root / c.image, rgb, tags[c.image])
        else:
            write_image(root / c.image, rgb)
    with Image.open(root / "before" / "000.png") as im:
        assert im.size == (96, 128)  # stored sideways
    (root / "cameras.json").write_text(json.dumps(cameras_to_json(gt)))
    out = tmp_path / "poses"
    summary = run_poses(root, out, PosesOptions(num_threads=1))
    assert summary["upright"] == 3 and not summary["resampled"]
    assert summary["image_dir"] == "images"
    assert summary["num_points_triangulated"] > 100
    photos = image_root(root, out / "cameras.json")
    assert photos == out / "images"
    for name in tags:
        with Image.open(photos / name) as im:
            assert im.size == (128, 96) and exif_orientation(photos / name) == 1
        assert np.array_equal(read_image(photos / name), read_image(src / name))
    import pycolmap

    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert {(k.width, k.height) for k in rec.cameras.values()} == {(128, 96)}
    # triangulated points reproject onto their keypoints in the rotated photos too
    cams = {c.image: c for c in load_cameras(out / "cameras.json")}
    for im in rec.images.values():
        if im.name not in tags:
            continue
        c = cams[im.name]
        errs = []
        for p in im.points2D:
            if p.has_point3D():
                X = rec.points3D[p.point3D_id].xyz
                q = c.K @ (c.w2c[:3, :3] @ X + c.w2c[:3, 3])
                errs.append(np.linalg.norm(q[:2] / q[2] - p.xy))
        assert len(errs) > 10 and np.median(errs) < 1.0, (im.name, len(errs))
