"""Known poses on real-capture-like input: frustum seeding when triangulation leaves too few
points, lens distortion (given in cameras.json or estimated by COLMAP) undistorted once in the
poses stage, and the ROS tf-yaml importer."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from gdiff.align import (angle_between_deg, orbit_radius, pose_errors, relative_rotation_errors,
                         rotation_angle_deg)
from gdiff.cameras import (PHOTO_CAMERAS, Camera, cameras_from_json, cameras_to_json, image_root,
                           load_cameras)
from gdiff.errors import SceneError
from gdiff.evaluate import find_eval_views
from gdiff.importers import detect_format, import_scene
from gdiff.io import read_image, write_image
from gdiff.sfm import PosesOptions, read_cameras_file, run_poses
from gdiff.sfm.seed import depth_range, empty_cells
from gdiff.sfm.refine_known import _place_untied, best_turn, common_turn, turn_between
from gdiff.sfm.undistort import boxes_to_pinhole, undistort_points, undistorted_camera
from gdiff.splat.ply import read_points

DIST = (-0.25, 0.08, 0.002, -0.0015, 0.0)  # strong barrel: ~6 px at the corners of 128x96


def _cv_K(c: Camera) -> np.ndarray:
    K = c.K.copy()
    K[:2, 2] -= 0.5
    return K


def _distort(img: np.ndarray, cam: Camera, dist) -> np.ndarray:
    """The photo a lens with ``dist`` (and ``cam``'s K) takes of the pinhole image ``img``."""
    gx, gy = np.meshgrid(np.arange(cam.width, dtype=np.float64),
                         np.arange(cam.height, dtype=np.float64))
    pts = np.stack([gx.ravel(), gy.ravel()], 1).reshape(-1, 1, 2)
    src = cv2.undistortPoints(pts, _cv_K(cam), np.asarray(dist), P=_cv_K(cam)).reshape(
        cam.height, cam.width, 2).astype(np.float32)
    return cv2.remap(img, src[..., 0], src[..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REFLECT)


@pytest.fixture(scope="module")
def gt_tiny(synth_tiny_dir):
    return read_cameras_file(Path(synth_tiny_dir) / "gt_cameras.json")


@pytest.fixture(scope="module")
def distorted_tiny(synth_tiny_dir, gt_tiny, tmp_path_factory):
    """The tiny scene photographed through a distorting lens (eval masks too)."""
    src = Path(synth_tiny_dir)
    dst = tmp_path_factory.mktemp("distorted") / "scene"
    for c in gt_tiny:
        write_image(dst / c.image, _distort(read_image(src / c.image), c, DIST))
    ref = gt_tiny[0]
    for m in sorted((src / "eval" / "masks").glob("*.png")):
        mask = cv2.imread(str(m), cv2.IMREAD_GRAYSCALE)
        gx, gy = np.meshgrid(np.arange(ref.width, dtype=np.float64),
                             np.arange(ref.height, dtype=np.float64))
        pts = np.stack([gx.ravel(), gy.ravel()], 1).reshape(-1, 1, 2)
        s = cv2.undistortPoints(pts, _cv_K(ref), np.asarray(DIST), P=_cv_K(ref)).reshape(
            ref.height, ref.width, 2).astype(np.float32)
        (dst / "eval" / "masks").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(dst / "eval" / "masks" / m.name),
                    cv2.remap(mask, s[..., 0], s[..., 1], cv2.INTER_NEAREST))
    return dst


# ------------------------------------------------------------------ cameras.json distortion


def test_cameras_json_distortion_forms_and_errors():
    base = {"width": 64, "height": 48, "fx": 50, "fy": 50, "cx": 32, "cy": 24,
            "frames": [{"image": "before/a.png", "c2w": np.eye(4).tolist()},
                       {"image": "after/a.png", "c2w": np.eye(4).tolist(),
                        "distortion": {"k1": 0.1, "p2": 0.01}}]}
    cams = cameras_from_json({**base, "distortion": [-0.1, 0.02, 0.0, 0.0, 0.003]})
    assert cams[0].dist == (-0.1, 0.02, 0.0, 0.0, 0.003)
    assert cams[1].dist == (0.1, 0.0, 0.0, 0.01, 0.0)
    again = cameras_from_json(cameras_to_json(cams))
    assert [c.dist for c in again] == [c.dist for c in cams]
    assert cameras_from_json({**base, "distortion": [0, 0, 0, 0]})[0].dist is None
    with pytest.raises(SceneError, match="distortion.*3 value"):
        cameras_from_json({**base, "distortion": [0.1, 0.2, 0.3]}, source="x.json")
    with pytest.raises(SceneError, match="unknown distortion key"):
        cameras_from_json({**base, "distortion": {"k7": 1.0}}, source="x.json")


# ------------------------------------------------------------------ seeding


def test_known_poses_without_sparse_points_seed_the_frusta(gt_tiny, tmp_path):
    """Photos with nothing to match (independent noise): no point can be triangulated, yet
    the fit gets a full point cloud inside the cameras' views, coloured from the photos. The
    eval photos are posed but seed nothing (they must not shape the fit)."""
    scene = tmp_path / "scene"
    rng = np.random.default_rng(0)
    cams = [c for c in gt_tiny if c.set in ("before", "after")]
    evals = [c for c in gt_tiny if c.set in ("eval_before", "eval_after")]
    assert evals
    for c in cams + evals:
        write_image(scene / c.image, rng.random((c.height, c.width, 3), dtype=np.float32))
    (scene / "cameras.json").write_text(json.dumps(cameras_to_json(cams + evals)))
    out = tmp_path / "poses"
    summary = run_poses(scene, out, PosesOptions(num_threads=1, seed_points_per_image=200),
                        images=[(c.image, c.set) for c in cams + evals])
    assert summary["num_points"] == summary["num_points_triangulated"] == 0
    assert summary["num_points_seeded"] == 200 * len(cams)
    xyz, rgb = read_points(out / "points.ply")
    assert len(xyz) == 200 * len(cams)
    # every point lies in front of the camera it was drawn for (round robin, 200 each) and
    # projects inside its image, onto a pixel of the colour it took
    for k, c in enumerate(cams):
        p = (c.w2c[:3, :3] @ xyz[200 * k:200 * (k + 1)].T.astype(np.float64)).T + c.w2c[:3, 3]
        assert (p[:, 2] > 0).all()
        uv = (c.K @ p.T).T
        uv = uv[:, :2] / uv[:, 2:]
        assert (uv >= -1e-3).all() and (uv[:, 0] <= c.width).all() and \
            (uv[:, 1] <= c.height).all()
        img = read_image(scene / c.image)
        col = img[np.minimum(uv[:, 1].astype(int), c.height - 1),
                  np.minimum(uv[:, 0].astype(int), c.width - 1)]
        assert np.abs(col - rgb[200 * k:200 * (k + 1)]).max() <= 1.5 / 255  # rgb in [0, 1]
    # no points to measure depths: the range comes from where the optical axes meet (the
    # orbit centre, ~2.1-2.35 m from the cameras), so it covers the table and the room
    near, far, how = depth_range(cams, np.zeros((0, 3)))
    assert "optical axes" in how and near < 1.0 and far > 4.0
    d = np.linalg.norm(xyz[:200] - cams[0].center, axis=1)
    assert d.min() >= near * 0.99 and d.max() <= far * 1.01 * 1.5


def test_seeding_threshold_is_per_image(synth_tiny_dir, gt_tiny, tmp_path):
    scene = tmp_path / "scene"
    scene.mkdir()
    for name in ("before", "after"):
        (scene / name).symlink_to((Path(synth_tiny_dir) / name).resolve())
    cams = [c for c in gt_tiny if c.set in ("before", "after")]
    (scene / "cameras.json").write_text(json.dumps(cameras_to_json(cams)))
    images = [(c.image, c.set) for c in cams]
    low = run_poses(scene, tmp_path / "low", PosesOptions(num_threads=1, min_points_per_image=1,
                                                          seed_cells=0), images=images)
    assert low["num_points_triangulated"] > 20 and low["num_points_seeded"] == 0
    # enough points overall: only the parts of each photo no point projects into are seeded
    part = run_poses(scene, tmp_path / "part", PosesOptions(num_threads=1, min_points_per_image=1,
                                                            seed_points_per_image=400,
                                                            seed_min_empty=0.0,
                                                            seed_sweep_extra=0),
                     images=images)
    xyz, _ = read_points(tmp_path / "part" / "points.ply")
    n_tri = part["num_points_triangulated"]
    cams = load_cameras(tmp_path / "part" / "cameras.json")  # as refined by the stage
    cells = empty_cells(cams, xyz[:n_tri], 16)
    # by default only when the empty cells are most of the photos (a sparse capture)
    assert np.mean([c.mean() for c in cells]) < PosesOptions().seed_min_empty
    assert low["num_points_triangulated"] == n_tri
    dflt = run_poses(scene, tmp_path / "dflt", PosesOptions(num_threads=1, min_points_per_image=1),
                     images=images)
    assert dflt["num_points_seeded"] == 0
    assert 0 < part["num_points_seeded"] < 400 * len(cams)
    assert part["num_points_seeded"] == sum(int(round(400 * c.mean())) for c in cells)
    start = n_tri
    for c, empty in zip(cams, cells):  # each seeded point lies in an empty cell of its photo
        m = int(round(400 * empty.mean()))
        p = (c.w2c[:3, :3] @ xyz[start:start + m].T.astype(np.float64)).T + c.w2c[:3, 3]
        uv = (c.K @ p.T).T
        uv = uv[:, :2] / uv[:, 2:]
        rows, cols = empty.shape
        r = np.clip((uv[:, 1] / c.height * rows).astype(int), 0, rows - 1)
        k = np.clip((uv[:, 0] / c.width * cols).astype(int), 0, cols - 1)
        assert empty[r, k].mean() > 0.99
        start += m
    high = run_poses(scene, tmp_path / "high",
                     PosesOptions(num_threads=1, min_points_per_image=10000,
                                  seed_points_per_image=50, seed_sweep_extra=0), images=images)
    assert high["num_points_triangulated"] == low["num_points_triangulated"]
    assert high["num_points_seeded"] == 50 * len(cams)
    xyz, _ = read_points(tmp_path / "high" / "points.ply")
    # depth range from the triangulated points: seeded points stay in and near the room
    # (|x|, |y| < 3.2 m, 0 <= z <= 2.8 m)
    near_room = (np.abs(xyz[:, :2]) < 5.0).all(1) & (xyz[:, 2] > -2.0) & (xyz[:, 2] < 4.5)
    assert near_room.mean() > 0.9


# ------------------------------------------------------------------ refinement


def test_roughly_known_poses_are_refined(synth_tiny_dir, gt_tiny, tmp_path):
    """A robot's poses: every camera turned by 1.2 deg and moved by 1 % of the camera spread
    (localisation, odometry, head joints), about 3 px on these 128 px photos. Bundle
    adjustment of the matched features brings them back near the true poses, in the frame and
    scale they were given in; used as given they stay off."""
    scene = tmp_path / "scene"
    scene.mkdir()
    for name in ("before", "after", "eval"):
        (scene / name).symlink_to((Path(synth_tiny_dir) / name).resolve())
    rng = np.random.default_rng(3)
    radius = orbit_radius(np.stack([c.center for c in gt_tiny]))
    given = []
    for c in gt_tiny:
        axis, step = rng.normal(size=3), rng.normal(size=3)
        c2w = c.c2w.copy()
        c2w[:3, :3] = Rotation.from_rotvec(np.deg2rad(1.2) * axis / np.linalg.norm(axis)
                                           ).as_matrix() @ c2w[:3, :3]
        c2w[:3, 3] += 0.01 * radius * step / np.linalg.norm(step)
        given.append(Camera(c.width, c.height, c.fx, c.fy, c.cx, c.cy, c2w, image=c.image,
                            set=c.set, time=c.time))
    (scene / "cameras.json").write_text(json.dumps(cameras_to_json(given)))
    summary = run_poses(scene, tmp_path / "poses", PosesOptions(num_threads=1))
    raw = run_poses(scene, tmp_path / "raw", PosesOptions(num_threads=1, refine_known=False))
    assert summary["refined_images"] == len(gt_tiny)
    assert summary["turned_to_partner"] == summary["turned_in_common"] == []
    assert summary["refined_rotation_deg"] == pytest.approx(1.2, abs=0.3)
    assert summary["mean_reprojection_error"] < 0.5 * raw["mean_reprojection_error"]
    refined = load_cameras(tmp_path / "poses" / "cameras.json")
    # the cameras agree with each other: relative rotations within the precision bundle
    # adjustment reaches on 128 px photos (about half a pixel; from the exact poses too)
    was, now = relative_rotation_errors(given, gt_tiny), relative_rotation_errors(refined, gt_tiny)
    assert np.median(was) > 1.4
    assert np.median(now) < 0.3 and now.max() < 0.6
    after = pose_errors(refined, gt_tiny)
    assert after["center_err_frac"].median() < 0.01
    # the given frame and scale are kept: no similarity needed to put them onto the truth
    assert after.attrs["scale"] == pytest.approx(1.0, abs=0.01)
    assert np.median([rotation_angle_deg(g.c2w[:3, :3].T @ c.c2w[:3, :3]) for c, g in zip(
        sorted(refined, key=lambda c: c.image), sorted(gt_tiny, key=lambda c: c.image))]) < 0.6


def test_known_pose_that_nothing_ties_takes_the_common_turn_of_the_others(
        synth_tiny_dir, gt_tiny, tmp_path):
    """One visit mislocalised as a whole (turned 1.5 deg about the vertical) and one photo no
    feature ties to anything (noise): bundle adjustment brings the visits together; the lone
    photo keeps its given centre and takes the correction the others share, and the summary
    names it."""
    scene = tmp_path / "scene"
    cams = [c for c in gt_tiny if c.set in ("before", "after")]
    lone = "after/004.png"
    rng = np.random.default_rng(0)
    for c in cams:
        img = (rng.random((c.height, c.width, 3), dtype=np.float32) if c.image == lone
               else read_image(Path(synth_tiny_dir) / c.image))
        write_image(scene / c.image, img)
    turn = Rotation.from_rotvec(np.deg2rad([0.0, 0.0, 1.5])).as_matrix()
    given = []
    for c in cams:
        c2w = c.c2w.copy()
        if c.time == 1:
            c2w[:3, :3] = turn @ c2w[:3, :3]
            c2w[:3, 3] = turn @ c2w[:3, 3]
        given.append(Camera(c.width, c.height, c.fx, c.fy, c.cx, c.cy, c2w, image=c.image,
                            set=c.set, time=c.time))
    (scene / "cameras.json").write_text(json.dumps(cameras_to_json(given)))
    summary = run_poses(scene, tmp_path / "poses", PosesOptions(num_threads=1),
                        images=[(c.image, c.set) for c in cams])
    assert summary["turned_in_common"] == [lone] and summary["turned_to_partner"] == []
    assert summary["refined_images"] == len(cams) - 1 and summary["kept_as_given"] == []
    out = {c.image: c for c in load_cameras(tmp_path / "poses" / "cameras.json")}
    was = {c.image: c for c in given}
    # the lone photo keeps its centre and takes the turn the refined ones share
    others = [n for n in out if n != lone]
    turn = common_turn([was[n].c2w for n in others], [out[n].c2w for n in others])
    np.testing.assert_allclose(out[lone].center, was[lone].center, atol=1e-9)
    np.testing.assert_allclose(out[lone].c2w[:3, :3], turn @ was[lone].c2w[:3, :3], atol=1e-9)

    def cross(cs):  # relative rotation errors between the visits, the lone photo left out
        c0 = [c for c in cs if c.time == 0]
        c1 = [c for c in cs if c.time == 1 and c.image != lone]
        return np.array([relative_rotation_errors([a, b], cams)[0] for a in c0 for b in c1])

    # the visits agree again, within what bundle adjustment reaches on 128 px photos
    assert np.median(cross(given)) > 1.4
    assert np.median(cross(out.values())) < 0.5


def _look(c2w_from: np.ndarray, rotvec_deg, shift=(0.0, 0.0, 0.0)) -> np.ndarray:
    """``c2w_from`` turned about its own centre by ``rotvec_deg`` (camera axes) and moved."""
    out = c2w_from.copy()
    out[:3, :3] = c2w_from[:3, :3] @ Rotation.from_rotvec(np.deg2rad(rotvec_deg)).as_matrix()
    out[:3, 3] = c2w_from[:3, 3] + np.asarray(shift)
    return out


def _project(cam: Camera, X: np.ndarray) -> np.ndarray:
    p = (cam.w2c[:3, :3] @ X.T).T + cam.w2c[:3, 3]
    uv = (cam.K @ p.T).T
    return uv[:, :2] / uv[:, 2:]


def _matches(a: Camera, b: Camera, rng, n=300, outliers=0.2, noise=0.5):
    """Pixels of random points 1-3 m in front of ``a`` in both cameras (noise, outliers)."""
    uv = rng.uniform([0, 0], [a.width, a.height], size=(n, 2))
    d = rng.uniform(1.0, 3.0, size=n)
    ray = (np.linalg.inv(a.K) @ np.c_[uv, np.ones(n)].T).T
    X = (a.c2w[:3, :3] @ (ray * d[:, None]).T).T + a.c2w[:3, 3]
    xa, xb = _project(a, X) + rng.normal(0, noise, (n, 2)), _project(b, X) + \
        rng.normal(0, noise, (n, 2))
    bad = rng.random(n) < outliers
    xb[bad] = rng.uniform([0, 0], [b.width, b.height], size=(int(bad.sum()), 2))
    return xa, xb


def test_turn_between_two_photos_from_one_place():
    """A robot back at a waypoint: the head turned by 3 deg and 2 cm off; the homography of
    their matches (1-3 m deep, 20 % false matches) gives the turn within a few tenths of a
    degree (the 2 cm of parallax is what is left)."""
    rng = np.random.default_rng(1)
    base = np.eye(4)
    a = Camera(640, 480, 540.0, 540.0, 320.0, 240.0, base, image="before/v04.png")
    b = Camera(640, 480, 540.0, 540.0, 320.0, 240.0, _look(base, [1.0, 2.5, 1.2], [0.02, 0, 0]),
               image="after/v04.png")
    M, k = turn_between(*_matches(a, b, rng), a.K, b.K, 4.0)
    true = b.c2w[:3, :3].T @ a.c2w[:3, :3]
    assert k > 200
    assert rotation_angle_deg(true.T @ M) < 0.5
    assert turn_between(np.zeros((3, 2)), np.zeros((3, 2)), a.K, b.K, 4.0) == (None, 0)


@pytest.mark.parametrize("off", [[0.0, 0.0, 0.02], [0.0, 0.0, -0.02], [0.0, 0.02, 0.0]])
def test_turn_with_a_baseline_given_a_few_centimetres_off(off):
    """A robot back at a waypoint 9 cm to the side, its given centre 2 cm off across that
    baseline: with the given baseline held (``turn_baseline: given``) the turn about the axis
    across it slides along the epipolar lines (more than 0.5 deg wrong); refined with the
    baseline's direction (``refined``), it comes out within a few tenths of a degree, and
    the support that decides the pairing is the same either way."""
    rng = np.random.default_rng(0)
    K = dict(width=640, height=480, fx=540.0, fy=540.0, cx=320.0, cy=240.0)
    b = Camera(**K, c2w=np.eye(4), image="before/v04.png")
    a = Camera(**K, c2w=_look(np.eye(4), [0, 1.5, 0.7], [-0.09, 0, 0]), image="after/v04.png")
    given = _look(a.c2w, [0.5, -0.5, 0], off)  # b at the origin: M0 and t in b's axes
    xa, xb = _matches(a, b, rng, n=150)
    held, k_held, _ = best_turn(xa, xb, a.K, b.K, given[:3, :3], given[:3, 3], 2.0)
    free, k_free, _ = best_turn(xa, xb, a.K, b.K, given[:3, :3], given[:3, 3], 2.0,
                                free_baseline=True)
    assert k_free >= 15 and abs(k_free - k_held) <= 0.1 * k_held
    assert rotation_angle_deg(a.c2w[:3, :3].T @ held) > 0.5
    assert rotation_angle_deg(a.c2w[:3, :3].T @ free) < 0.3


@pytest.mark.parametrize("length", [0.0, 0.03, 0.3])
def test_refined_baseline_turn_at_any_baseline_length(length):
    """From one place (no baseline) to 30 cm apart, the given centre 2 cm off across the
    baseline: the turn refined with the baseline's direction is within a few tenths of a
    degree of the true one, never further off than the one fitted with it held, and the
    support that decides the pairing stays the held fit's."""
    K = dict(width=640, height=480, fx=540.0, fy=540.0, cx=320.0, cy=240.0)
    for seed in range(3):
        rng = np.random.default_rng(seed)
        b = Camera(**K, c2w=np.eye(4), image="before/v04.png")
        a = Camera(**K, c2w=_look(np.eye(4), [0, 1.5, 0.7], [-length, 0, 0]),
                   image="after/v04.png")
        given = _look(a.c2w, [0.5, -0.5, 0], [0.0, 0.02, 0.0])
        xa, xb = _matches(a, b, rng, n=150)
        held, k_held, _ = best_turn(xa, xb, a.K, b.K, given[:3, :3], given[:3, 3], 2.0)
        free, k_free, _ = best_turn(xa, xb, a.K, b.K, given[:3, :3], given[:3, 3], 2.0,
                                    free_baseline=True)
        err_free = rotation_angle_deg(a.c2w[:3, :3].T @ free)
        assert err_free < 0.2
        assert err_free <= rotation_angle_deg(a.c2w[:3, :3].T @ held) + 0.05
        assert k_free == k_held


def test_turn_baseline_option():
    """``poses.turn_baseline`` takes given or refined; by default the baseline's direction is
    refined with the turn."""
    assert PosesOptions().turn_baseline == "refined"
    with pytest.raises(ValueError, match="turn_baseline"):
        PosesOptions(turn_baseline="free")


def test_angle_between_two_photos_for_the_log():
    """The poses log gives, per photo turned to agree with another, the angle between the two
    as placed and as given: either order, whatever the centres."""
    a = _look(np.eye(4), [0, 30, 0], [1.0, 2.0, 0.5])
    b = _look(a, [0, 7.5, 0], [0.3, 0, 0])
    assert angle_between_deg(b, a) == pytest.approx(7.5)
    assert angle_between_deg(a, b) == pytest.approx(7.5)


def test_untied_photos_are_turned_to_agree_with_a_photo_from_the_same_place():
    """Poses for photos bundle adjustment could not tie: one shares matches with a refined
    photo of its waypoint (turned to agree with it, moved with it), a pair of untied photos of
    another waypoint (the before one keeps its given centre and takes the common correction,
    the after one is turned to it), and a photo sharing nothing (given centre, common
    correction)."""
    rng = np.random.default_rng(2)
    K = dict(width=640, height=480, fx=540.0, fy=540.0, cx=320.0, cy=240.0)
    truth = {"before/v01.png": _look(np.eye(4), [0, 0, 0]),
             "after/v01.png": _look(np.eye(4), [0, 1.5, 0], [0.03, 0, 0]),
             "before/v04.png": _look(np.eye(4), [0, 90, 0], [1.0, 0, 1.0]),
             "after/v04.png": _look(np.eye(4), [0.5, 91, 0], [1.02, 0, 1.0]),
             "after/v05.png": _look(np.eye(4), [0, 180, 0], [0, 0, 2.0])}
    err = {"before/v01.png": [1.0, 0, 0], "after/v01.png": [0, -2.0, 0.5],
           "before/v04.png": [0, 0, 0], "after/v04.png": [1.5, 1.5, 0], "after/v05.png": [0, 2, 0]}
    cams = {n: Camera(**K, c2w=_look(t, err[n]), image=n, set=n.split("/")[0],
                      time=0 if n.startswith("before") else 1) for n, t in truth.items()}
    real = {n: Camera(**K, c2w=t, image=n) for n, t in truth.items()}
    matches = {}
    for a, b in (("after/v01.png", "before/v01.png"), ("after/v04.png", "before/v04.png")):
        xa, xb = _matches(real[a], real[b], rng)
        matches[(a, b)], matches[(b, a)] = (xa, xb), (xb, xa)
    # bundle adjustment put before/v01 at its true pose (shifted by a frame offset)
    offset = _look(np.eye(4), [0, 0, 0], [0.1, 0, 0])
    placed = {"before/v01.png": offset @ truth["before/v01.png"]}
    loose = ["before/v04.png", "after/v01.png", "after/v04.png", "after/v05.png"]
    turn = Rotation.from_rotvec(np.deg2rad([0.0, 0.7, 0.0])).as_matrix()
    poses, partners, anchored = _place_untied(loose, placed, cams, matches, 15, 4.0, turn)
    assert {k: v[0] for k, v in partners.items()} == {"after/v01.png": "before/v01.png",
                                                      "after/v04.png": "before/v04.png"}
    assert anchored == ["before/v04.png", "after/v05.png"]
    for n in anchored:  # their given centre, turned by the common correction
        np.testing.assert_allclose(poses[n][:3, 3], cams[n].center)
        np.testing.assert_allclose(poses[n][:3, :3], turn @ cams[n].c2w[:3, :3])
    both = {**placed, **poses}
    for a, (b, _) in partners.items():  # relative rotations of the partners now as true
        got = both[b][:3, :3].T @ both[a][:3, :3]
        want = truth[b][:3, :3].T @ truth[a][:3, :3]
        assert rotation_angle_deg(want.T @ got) < 0.5  # parallax of 2-3 cm at 1-3 m
        was = cams[b].c2w[:3, :3].T @ cams[a].c2w[:3, :3]
        assert rotation_angle_deg(want.T @ was) > 1.4
    # moved with its partner: the given offset between the centres, turned as the partner was
    np.testing.assert_allclose(poses["after/v01.png"][:3, 3],
                               placed["before/v01.png"][:3, 3] + cams["after/v01.png"].center
                               - cams["before/v01.png"].center, atol=1e-9)


# ------------------------------------------------------------------ undistortion


def _pinhole_error(img: np.ndarray, c: Camera, g: Camera, synth: Path) -> float:
    """Mean absolute difference (4 px border left out) between ``img`` and the ground-truth
    pinhole photo of ``g`` seen through ``c``'s intrinsics (same pose)."""
    gx, gy = np.meshgrid(np.arange(c.width, dtype=np.float64),
                         np.arange(c.height, dtype=np.float64))
    ray = np.linalg.inv(_cv_K(c)) @ np.stack([gx.ravel(), gy.ravel(), np.ones(gx.size)])
    src = (_cv_K(g) @ ray)[:2].reshape(2, c.height, c.width).astype(np.float32)
    want = cv2.remap(read_image(synth / g.image), src[0], src[1], cv2.INTER_LINEAR)
    return float(np.abs(img - want)[4:-4, 4:-4].mean())


def _check_undistorted(out: Path, scene: Path, gt: dict[str, Camera], synth: Path,
                       fit_zoom: bool = False) -> list:
    """cameras.json points at undistorted photos that match the pinhole ground truth (mean
    absolute difference < 0.025, and well below that of the distorted photo). ``fit_zoom``:
    up to a focal-length scale within +-3 % (self-calibration's uncertainty on tiny photos)."""
    data = json.loads((out / "cameras.json").read_text())
    assert data["image_dir"] == "images" and "distortion" not in data
    assert image_root(scene, out / "cameras.json") == out / "images"
    cams = load_cameras(out / "cameras.json")
    zooms = np.linspace(0.97, 1.03, 31) if fit_zoom else [1.0]
    for c in cams[::5]:
        got, raw = read_image(out / "images" / c.image), read_image(scene / c.image)
        errs = {}
        for name, img in (("got", got), ("raw", raw)):
            errs[name] = min(_pinhole_error(img, Camera(
                c.width, c.height, c.fx * z, c.fy * z, c.cx, c.cy, c.c2w), gt[c.image], synth)
                for z in zooms)
        assert errs["got"] < 0.025, (c.image, errs)
        assert errs["raw"] > 1.5 * errs["got"], (c.image, errs)  # undistorting mattered
    return cams


@pytest.fixture(scope="module")
def undistorted_poses(distorted_tiny, gt_tiny, tmp_path_factory):
    """The poses stage on the distorted tiny scene, given its cameras with the distortion:
    (poses folder, summary, the cameras given)."""
    scene = distorted_tiny
    given = [Camera(c.width, c.height, c.fx, c.fy, c.cx, c.cy, c.c2w, image=c.image,
                    set=c.set, time=c.time, dist=DIST) for c in gt_tiny]
    (scene / "cameras.json").write_text(json.dumps(cameras_to_json(given)))
    out = tmp_path_factory.mktemp("undistorted") / "poses"
    try:
        summary = run_poses(scene, out, PosesOptions(num_threads=1, refine_known=False))
    finally:
        (scene / "cameras.json").unlink()
    return out, summary, given


def test_distortion_in_cameras_json_is_undistorted(undistorted_poses, distorted_tiny, gt_tiny,
                                                   synth_tiny_dir):
    import pycolmap

    scene = distorted_tiny
    out, summary, given = undistorted_poses
    assert summary["undistorted"] and summary["num_points_triangulated"] > 100
    gt = {c.image: c for c in gt_tiny}
    cams = _check_undistorted(out, scene, gt, Path(synth_tiny_dir))
    pin = undistorted_camera(given[0])
    assert (cams[0].fx, cams[0].cy) == pytest.approx((pin.fx, pin.cy))
    for c in cams:
        assert np.allclose(c.c2w, gt[c.image].c2w)
    # triangulated points reproject onto their (undistorted) keypoints mapped into the
    # ground-truth pinhole images, through the ground-truth cameras
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    errs = []
    for im in rec.images.values():
        g, c = gt[im.name], next(k for k in cams if k.image == im.name)
        for p in im.points2D:
            if not p.has_point3D():
                continue
            x_gt = (_cv_K(g) @ np.linalg.inv(_cv_K(c)) @ np.r_[p.xy - 0.5, 1.0])[:2] + 0.5
            X = rec.points3D[p.point3D_id].xyz
            q = g.K @ (g.w2c[:3, :3] @ X + g.w2c[:3, 3])
            errs.append(np.linalg.norm(q[:2] / q[2] - x_gt))
    assert len(errs) > 300 and np.median(errs) < 0.7 and np.mean(errs) < 1.0
    # eval masks were undistorted with their views; evaluate finds them in the image root
    views = find_eval_views(image_root(scene, out / "cameras.json"), out / "cameras.json")
    assert len(views) == 3 and all(v.camera is not None for v in views)
    assert all(Path(v.mask).is_relative_to(out / "images") for v in views)


def test_boxes_on_distorted_photos_follow_the_undistortion(undistorted_poses):
    """The poses stage keeps the photos' own (distorted) cameras beside cameras.json, and a box
    drawn on a distorted photo becomes the box that holds the same pixels in the undistorted
    image (its edges bend: the box of the mapped edges is that of the whole mapped area)."""
    out, _, given = undistorted_poses
    photo = {c.image: c for c in load_cameras(out / PHOTO_CAMERAS)}
    cams = {c.image: c for c in load_cameras(out / "cameras.json")}
    assert set(photo) == {c.image for c in given}
    c = given[0]
    src, pin = photo[c.image], cams[c.image]
    assert src.dist == pytest.approx(DIST) and (src.width, src.height) == (c.width, c.height)
    assert pin.dist is None and np.allclose(src.c2w, pin.c2w)
    w, h = c.width, c.height
    boxes = np.array([[0.1 * w, 0.1 * h, 0.5 * w, 0.45 * h], [0.3 * w, 0.4 * h, 0.9 * w, 0.9 * h]])
    got = boxes_to_pinhole(boxes, src, pin)
    for b, g in zip(boxes, got):
        xs, ys = np.meshgrid(np.linspace(b[0], b[2], 80), np.linspace(b[1], b[3], 80))
        p = undistort_points(np.stack([xs.ravel(), ys.ravel()], 1), src, pin)
        want = np.array([p[:, 0].min(), p[:, 1].min(), p[:, 0].max(), p[:, 1].max()])
        want = want.clip(0, [pin.width, pin.height, pin.width, pin.height])
        assert np.abs(g - want).max() < 0.2, (g, want)
    assert np.abs(got - boxes).max() > 1.0  # undistortion moved them
    # under pincushion distortion an edge's middle goes out farthest: not the corners' box
    pc = replace(src, dist=(0.4, 0.1, 0.0, 0.0, 0.0))
    b = np.array([0.2 * w, 0.2 * h, 0.8 * w, 0.8 * h])
    xs, ys = np.meshgrid(np.linspace(b[0], b[2], 81), np.linspace(b[1], b[3], 81))
    p = undistort_points(np.stack([xs.ravel(), ys.ravel()], 1), pc, pin)
    want = np.array([p[:, 0].min(), p[:, 1].min(), p[:, 0].max(), p[:, 1].max()])
    corners = undistort_points(b[[0, 1, 2, 1, 0, 3, 2, 3]].reshape(4, 2), pc, pin)
    assert np.abs(boxes_to_pinhole(b[None], pc, pin)[0] - want).max() < 0.2
    assert np.abs(np.r_[corners.min(0), corners.max(0)] - want).max() > 0.5


def test_fit_on_the_undistorted_photos_matches_the_pinhole_fit(undistorted_poses, distorted_tiny,
                                                               gt_tiny, synth_tiny_dir,
                                                               tmp_path):
    """A scene photographed through a distorting lens, undistorted by the poses stage and
    fitted, renders the held-out pinhole views about as well as a fit to the pinhole photos
    themselves (same cameras, same start points), and better than a fit that takes the
    distorted photos for pinhole ones."""
    import torch

    from gdiff.cameras import save_cameras
    from gdiff.splat.losses import psnr
    from gdiff.splat.model import load_model
    from gdiff.splat.render import render
    from gdiff.splat.train import fit_scene

    from test_fit import small_options

    out, _, _ = undistorted_poses
    train = [c for c in gt_tiny if c.set in ("before", "after")]
    save_cameras(tmp_path / "pinhole.json", train)
    runs = {"undistorted": (distorted_tiny, out / "cameras.json"),
            "pinhole": (Path(synth_tiny_dir), tmp_path / "pinhole.json"),
            "distorted as pinhole": (distorted_tiny, tmp_path / "pinhole.json")}
    score = {}
    for name, (scene, cams) in runs.items():
        fit_scene(scene, cams, out / "points.ply", tmp_path / name,
                  small_options(max_side=128, checkpoint_every=0, fine_iters=60, deform=False),
                  device="cpu")
        model = load_model(tmp_path / name / "model.pt", "cpu")
        vals = []
        with torch.no_grad():
            for c in (c for c in gt_tiny if c.set in ("eval_before", "eval_after")):
                r = render(model, [c], c.time)["rgb"][0].clamp(0, 1)
                truth = torch.from_numpy(read_image(Path(synth_tiny_dir) / c.image))
                vals.append(float(psnr(r, truth)))
        score[name] = float(np.mean(vals))
    print("held-out PSNR:", {k: round(v, 2) for k, v in score.items()})
    assert score["undistorted"] > score["pinhole"] - 1.0
    assert score["undistorted"] > score["distorted as pinhole"] + 1.0


def test_colmap_estimates_and_removes_distortion(distorted_tiny, gt_tiny, synth_tiny_dir,
                                                 tmp_path):
    scene = distorted_tiny
    assert not (scene / "cameras.json").exists()
    out = tmp_path / "poses"
    summary = run_poses(scene, out, PosesOptions(num_threads=1, camera_model="OPENCV"))
    assert summary["source"] == "colmap" and summary["undistorted"]
    gt = {c.image: c for c in gt_tiny}
    # the estimated focal length is ~1 % off on 128x96 photos (it trades off against k1)
    cams = _check_undistorted(out, scene, gt, Path(synth_tiny_dir), fit_zoom=True)
    err = pose_errors(cams, [gt[c.image] for c in cams])
    # tiny is 128x96: the same bounds as the pinhole registration test in test_sfm.py
    assert err["rot_err_deg"].median() < 2.0 and err["center_err_frac"].median() < 0.05, err


# ------------------------------------------------------------------ ROS tf-yaml importer


def _tf_source(root: Path) -> dict[str, np.ndarray]:
    """A made-up robot capture: 2 + 2 photos, provenance names, two tf YAML files, and a
    ROS CameraInfo. Returns the true c2w per original frame name."""
    rng = np.random.default_rng(3)
    truth, entries = {}, {"scene1": [], "scene2": []}
    views = []
    for k, (st, scene) in enumerate([("before", "scene1"), ("before", "scene1"),
                                     ("after", "scene2"), ("after", "scene2")]):
        name = f"v{k % 2:02d}.png"
        frame = f"rgb_image_raw-{1000 + k}.png"
        write_image(root / st / name, rng.random((48, 64, 3), dtype=np.float32))
        q = [float(v) for v in Rotation.random(random_state=k).as_quat()]  # x, y, z, w
        t = [float(v) for v in rng.normal(size=3)]
        c2w = np.eye(4)
        c2w[:3, :3] = Rotation.from_quat(q).as_matrix()
        c2w[:3, 3] = t
        truth[f"{st}/{name}"] = c2w
        sign = -1.0 if k == 1 else 1.0  # q and -q are the same rotation
        entries[scene].append({
            "file_name": frame, "id": k, "origin_frame": "/map",
            "target_frame": "/head_rgbd_sensor_rgb_frame", "timestamp": 1.0 + k,
            "rotation": {"w": sign * q[3], "x": sign * q[0], "y": sign * q[1],
                         "z": sign * q[2]},
            "translation": {"x": t[0], "y": t[1], "z": t[2]}})
        views.append({"set": st, "name": name, "src_path": f"data/{scene}/{frame}"})
    robot = root / "robot"
    robot.mkdir()
    for scene, e in entries.items():
        (robot / f"{scene}_transformations.yaml").write_text(yaml.safe_dump(e))
    (robot / "provenance.json").write_text(json.dumps({"views": views}))
    (robot / "camera_info.json").write_text(json.dumps({
        "height": 48, "width": 64, "distortion_model": "plumb_bob",
        "D": [0.06, -0.2, -0.0001, -0.001, 0.15],
        "K": [50.0, 0, 31.0, 0, 51.0, 23.5, 0, 0, 1]}))
    return truth


def test_tf_yaml_import(tmp_path):
    src = tmp_path / "robot_capture"
    truth = _tf_source(src)
    assert detect_format(src) == "tf-yaml"
    out = import_scene("tf-yaml", src, tmp_path / "scene")
    cams = {c.image: c for c in read_cameras_file(out / "cameras.json")}
    assert sorted(cams) == sorted(truth)
    for name, c in cams.items():
        assert np.allclose(c.c2w, truth[name], atol=1e-9), name
        assert c.set == name.split("/")[0]
        # ROS pixel centres are integers, gdiff's at +0.5
        assert (c.fx, c.fy, c.cx, c.cy) == (50.0, 51.0, 31.5, 24.0)
        assert c.dist == (0.06, -0.2, -0.0001, -0.001, 0.15)
    meta = json.loads((out / "import.json").read_text())
    assert meta["known_poses"] and meta["counts"] == {"before": 2, "after": 2}


def test_tf_yaml_import_errors(tmp_path):
    src = tmp_path / "robot_capture"
    _tf_source(src)
    frames = yaml.safe_load((src / "robot" / "scene2_transformations.yaml").read_text())
    (src / "robot" / "scene2_transformations.yaml").write_text(yaml.safe_dump(frames[:1]))
    with pytest.raises(SceneError, match="no pose in .* for 1 photo.*after/v01.png"):
        import_scene("tf-yaml", src, tmp_path / "a")
    assert not (tmp_path / "a").exists()
    del frames[0]["rotation"]
    (src / "robot" / "scene2_transformations.yaml").write_text(yaml.safe_dump(frames))
    with pytest.raises(SceneError, match="scene2_transformations.yaml: entry 0: needs"):
        import_scene("tf-yaml", src, tmp_path / "b")
    (src / "robot" / "camera_info.json").unlink()
    with pytest.raises(SceneError, match="camera_info"):
        import_scene("tf-yaml", src, tmp_path / "c")


# ------------------------------------------------------------------ plane sweep


def test_seed_depths_from_the_plane_sweep_match_the_rendered_depth(synth_tiny_dir):
    """Where a textured patch of one photo is seen from elsewhere by another photo of the
    scene, the seed takes the depth at which they match: on a rendered scene that is the
    rendered depth. Untextured photos and a photo from the same place give no depth."""
    from gdiff.synth import build_scene
    from gdiff.sfm.seed import _grey, seed_frustum_points, sweep_depths

    scene = build_scene("tiny", 0)  # the scene of synth_tiny_dir
    cams = read_cameras_file(Path(synth_tiny_dir) / "gt_cameras.json")
    cams = [c for c in cams if c.set == "before"]
    truth = [scene.render(c, "before")["depth"] for c in cams]
    greys = [_grey(read_image(Path(synth_tiny_dir) / c.image)) for c in cams]
    rng = np.random.default_rng(0)
    c = cams[0]
    u = rng.uniform(8, c.width - 8, 400)
    v = rng.uniform(8, c.height - 8, 400)
    z = truth[0][v.astype(int), u.astype(int)].astype(np.float64)
    near, far = 0.5 * z.min(), 1.5 * z.max()
    step = np.log(far / near) / 63  # the sweep's depth step at this range (64 depths)
    d = sweep_depths(cams, greys, 0, u, v, near, far)
    found = np.isfinite(d)
    assert found.mean() > 0.3  # the textured part of the photo
    err = np.abs(np.log(d[found] / z[found]))
    assert np.median(err) < step and (err < 0.2).mean() > 0.9
    # nothing to match: no depth
    flat = [np.full_like(g, 0.5) for g in greys]
    assert np.isnan(sweep_depths(cams, flat, 0, u, v, near, far)).all()
    # the only other photo is taken from the same place: it cannot tell depths apart
    twin = [c, dataclasses.replace(c, image="twin.png")]
    assert np.isnan(sweep_depths(twin, [greys[0], greys[0]], 0, u, v, near, far)).all()

    # seeding: 100 points per photo, swept where the sweep finds a depth, plus the extra
    # swept points; the first photo's swept points lie on its rendered surface
    n = [100] * len(cams)
    xyz, rgb, swept = seed_frustum_points(cams, synth_tiny_dir, n, near, far, extra=3)
    assert len(xyz) > sum(n) and swept[sum(n):].all() and 0 < swept[:sum(n)].sum() < sum(n)
    plain, _, none = seed_frustum_points(cams, synth_tiny_dir, n, near, far, sweep=False)
    assert len(plain) == sum(n) and not none.any()
    p = xyz[:100][swept[:100]].astype(np.float64) @ c.w2c[:3, :3].T + c.w2c[:3, 3]
    col = np.clip((c.fx * p[:, 0] / p[:, 2] + c.cx).astype(int), 0, c.width - 1)
    row = np.clip((c.fy * p[:, 1] / p[:, 2] + c.cy).astype(int), 0, c.height - 1)
    err = np.abs(np.log(p[:, 2] / truth[0][row, col]))
    assert np.median(err) < step and (err < 0.2).mean() > 0.9
