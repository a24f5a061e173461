"""Importers: tiny fake trees in each public dataset's layout -> gdiff scene folders."""

import json

import numpy as np
import pytest

from gdiff.cameras import look_at, load_cameras
from gdiff.errors import ConfigError, SceneError
from gdiff.importers import detect_format, import_scene, main
from gdiff.io import read_mask, write_image

GL = np.diag([1.0, -1.0, -1.0, 1.0])


def _img(path, w=16, h=12, seed=0):
    rng = np.random.default_rng(seed)
    write_image(path, rng.uniform(0, 1, (h, w, 3)))
    return path


def _mask(path, w=16, h=12, box=(2, 2, 6, 6), value=255):
    m = np.zeros((h, w), np.uint8)
    x0, y0, x1, y1 = box
    m[y0:y1, x0:x1] = value
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), m)
    return path


def _c2w(i):
    return look_at([3.0 * np.cos(i), 3.0 * np.sin(i), 1.0], [0, 0, 0])


def _frames(cams_path):
    return {c.image: c for c in load_cameras(cams_path)}


# ------------------------------------------------------------------------------ C-NeRF / LLFF


def _llff_row(c2w, h, w, f):
    P = np.zeros((3, 5))
    P[:, 0], P[:, 1], P[:, 2] = c2w[:3, 1], c2w[:3, 0], -c2w[:3, 2]  # down, right, back
    P[:, 3] = c2w[:3, 3]
    P[:, 4] = (h, w, f)
    return np.concatenate([P.ravel(), [0.5, 10.0]])


def _cnerf_tree(root, joint=True):
    poses = np.stack([_llff_row(_c2w(i), 24, 32, 40.0) for i in range(6)])
    for k, name in enumerate(("chess1", "chess2")):
        for i in range(3):
            _img(root / name / "images" / f"IMG_{i:03d}.JPG".replace("JPG", "png"), seed=k * 3 + i)
        np.save(root / name / "poses_bounds.npy",
                poses if joint else poses[3 * k:3 * k + 3])


def test_llff_axes_hand_checked(tmp_path):
    # LLFF rotation columns (down, right, back) of an OpenCV identity camera
    from gdiff.importers._common import llff_to_opencv

    P = np.array([[0, 1, 0, 1.0], [1, 0, 0, 2.0], [0, 0, -1, 3.0]])
    c2w = llff_to_opencv(P)
    assert np.allclose(c2w[:3, :3], np.eye(3)) and np.allclose(c2w[:3, 3], [1, 2, 3])


def test_cnerf_joint_poses(tmp_path):
    _cnerf_tree(tmp_path / "src")
    assert detect_format(tmp_path / "src") == "cnerf"
    out = import_scene("C-NeRF", tmp_path / "src", tmp_path / "scene")
    assert sorted(p.name for p in (out / "before").iterdir()) == [
        "IMG_000.png", "IMG_001.png", "IMG_002.png"]
    assert (out / "after" / "IMG_000.png").is_symlink()
    assert not (out / "eval").exists()
    fr = _frames(out / "cameras.json")
    assert len(fr) == 6
    cam = fr["after/IMG_001.png"]
    assert cam.set == "after" and cam.time == 1
    assert np.allclose(cam.c2w, _c2w(4))  # after images take the last rows
    # intrinsics scaled from the 32x24 poses to the 16x12 files; principal point at the centre
    assert (cam.width, cam.height, cam.fx, cam.cx, cam.cy) == (16, 12, 20.0, 8.0, 6.0)
    meta = json.loads((out / "import.json").read_text())
    assert meta["known_poses"] and meta["counts"] == {"before": 3, "after": 3}


def test_cnerf_separate_poses_and_errors(tmp_path):
    _cnerf_tree(tmp_path / "src", joint=False)
    out = import_scene("cnerf", tmp_path / "src", tmp_path / "scene", copy=True)
    assert not (out / "cameras.json").exists()
    assert not (out / "before" / "IMG_000.png").is_symlink()
    (tmp_path / "src" / "chess2" / "poses_bounds.npy").unlink()
    with pytest.raises(SceneError, match="chess2/poses_bounds.npy"):
        import_scene("cnerf", tmp_path / "src", tmp_path / "scene2")
    assert not (tmp_path / "scene2").exists()
    assert not list(tmp_path.glob(".scene2.import-*"))  # temp folder cleaned up
    with pytest.raises(SceneError, match="already exists"):
        import_scene("cnerf", tmp_path / "src", out)
    with pytest.raises(ConfigError, match="unknown dataset format"):
        import_scene("nerf-cd", tmp_path / "src", tmp_path / "x")


# ------------------------------------------------------------------------------------ 3DGS-CD


def _gscd_tree(root, mask_names):
    frames = []
    for folder, k in (("rgb", 0), ("rgb_new", 10)):
        for i in range(4):
            _img(root / folder / f"frame_{i:05d}.png", seed=k + i)
            frames.append({"file_path": f"{folder}/frame_{i:05d}.png",
                           "transform_matrix": (_c2w(k + i) @ GL).tolist()})
    for name in mask_names:
        _mask(root / "masks_gt" / name, value=1)  # 0/1 masks are fine
    (root / "transforms.json").write_text(json.dumps(
        {"w": 32, "h": 24, "fl_x": 30.0, "fl_y": 31.0, "cx": 16.0, "cy": 12.0,
         "frames": frames}))


@pytest.mark.parametrize("names", [["frame_00001.png", "frame_00003.png"],
                                   ["mask_00001.png", "mask_00003.png"],
                                   ["0.png", "1.png"]])
def test_3dgscd(tmp_path, names):
    _gscd_tree(tmp_path / "src", names)
    assert detect_format(tmp_path / "src") == "3dgscd"
    out = import_scene("3DGS-CD", tmp_path / "src", tmp_path / "scene")
    assert len(list((out / "before").iterdir())) == 4
    assert sorted(p.name for p in (out / "after").iterdir()) == ["frame_00000.png",
                                                                 "frame_00002.png"]
    assert sorted(p.name for p in (out / "eval" / "after").iterdir()) == ["frame_00001.png",
                                                                          "frame_00003.png"]
    assert not (out / "eval" / "before").exists()
    m = read_mask(out / "eval" / "masks" / "frame_00003.png")
    assert m.sum() == 16 and m[3, 3]
    fr = _frames(out / "cameras.json")
    cam = fr["eval/after/frame_00003.png"]
    assert cam.set == "eval_after" and np.allclose(cam.c2w, _c2w(13))  # OpenGL -> OpenCV
    assert (cam.fx, cam.fy, cam.cx) == (15.0, 15.5, 8.0)
    assert np.allclose(fr["before/frame_00002.png"].c2w, _c2w(2))


def test_3dgscd_missing_folder_named(tmp_path):
    _gscd_tree(tmp_path / "src", ["frame_00001.png"])
    import shutil

    shutil.rmtree(tmp_path / "src" / "masks_gt")
    with pytest.raises(SceneError, match="masks_gt"):
        import_scene("3dgscd", tmp_path / "src", tmp_path / "scene")


# ------------------------------------------------------------------------------------- PASLCD


def _write_colmap(sparse, names_c2w, w=16, h=12):
    import pycolmap

    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(camera_id=1, model="PINHOLE", width=w,
                                                    height=h, params=[14.0, 15.0, 8.0, 6.0]))
    for i, (name, c2w) in enumerate(names_c2w, start=1):
        w2c = np.linalg.inv(c2w)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3])
        rec.add_image_with_trivial_frame(pycolmap.Image(image_id=i, name=name, camera_id=1),
                                         pose)
    sparse.mkdir(parents=True)
    rec.write(str(sparse))


def test_paslcd(tmp_path):
    inst = tmp_path / "Cantina" / "Instance_1"
    posed = []
    for i in range(3):
        n = f"Inst_1_IMG_{i:04d}.png"
        _img(inst / "input_orig" / n, seed=i)
        posed.append((n, _c2w(i)))
        t = f"Inst_1_test_IMG_{i:04d}.png"
        _img(inst / "input_orig_test" / t, seed=10 + i)
        posed.append((t, _c2w(10 + i)))
        if i != 1:
            _mask(inst / "gt_mask" / t)
    (inst / "changes.txt").write_text("chair moved\nbag added\n")
    _write_colmap(inst / "sparse" / "0", posed)
    assert detect_format(inst) == "paslcd"
    with pytest.raises(SceneError, match="Instance_1"):
        import_scene("paslcd", tmp_path / "Cantina", tmp_path / "x")
    out = import_scene("paslcd", inst, tmp_path / "scene")
    assert len(list((out / "before").iterdir())) == 3
    assert len(list((out / "after").iterdir())) == 3
    assert sorted(p.stem for p in (out / "eval" / "after").iterdir()) == [
        "Inst_1_test_IMG_0000", "Inst_1_test_IMG_0002"]
    fr = _frames(out / "cameras.json")
    assert len(fr) == 8
    cam = fr["eval/after/Inst_1_test_IMG_0002.png"]
    assert np.allclose(cam.c2w, _c2w(12), atol=1e-9)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (14.0, 15.0, 8.0, 6.0)
    meta = json.loads((out / "import.json").read_text())
    assert any("bag added" in n for n in meta["notes"])


def test_paslcd_without_poses_and_missing_masks(tmp_path):
    inst = tmp_path / "Zen" / "Instance_2"
    for i in range(3):
        _img(inst / "input_orig" / f"a{i}.png", seed=i)
        _img(inst / "input_orig_test" / f"t{i}.png", seed=5 + i)
    with pytest.raises(SceneError, match="gt_mask"):
        import_scene("paslcd", inst, tmp_path / "scene")
    _mask(inst / "gt_mask" / "t2.png")
    out = import_scene("paslcd", inst, tmp_path / "scene")
    assert not (out / "cameras.json").exists()
    assert [p.name for p in (out / "eval" / "masks").iterdir()] == ["t2.png"]


# -------------------------------------------------------------------------------------- CCS3D


def test_ccs3d(tmp_path):
    src = tmp_path / "CCS3D" / "desk"
    posed = []
    for i in range(2):
        for d, k in (("train-pre", 0), ("train-post", 5)):
            n = f"{d}_{i:03d}.png"
            _img(src / d / n, seed=k + i)
            posed.append((n, _c2w(k + i)))
    # test views 010 (same camera before and after), 011 (pre only), 012 (post only)
    for name, d, pose in (("pre_010.png", "test-pre", 20), ("post_010.png", "test-post", 20),
                          ("pre_011.png", "test-pre", 21), ("post_012.png", "test-post", 22),
                          ("pre_013.png", "test-pre", 23), ("post_013.png", "test-post", 24)):
        _img(src / d / name, seed=pose)
        posed.append((name, _c2w(pose)))
    _mask(src / "gt-pre-mask" / "gt_010.png", box=(0, 0, 4, 4))
    _mask(src / "gt-post-mask" / "gt_010.png", box=(8, 6, 12, 10))
    _mask(src / "gt-pre-mask" / "gt_011.png")
    _mask(src / "gt-post-mask" / "gt_012.png")
    _mask(src / "gt-pre-mask" / "gt_013.png")  # same number, another camera: not a pair
    _mask(src / "gt-post-mask" / "gt_013.png")
    _write_colmap(src / "sparse" / "0", posed)
    assert detect_format(src) == "ccs3d"
    out = import_scene("ccs3d", src, tmp_path / "scene")
    ev = out / "eval"
    assert sorted(p.stem for p in (ev / "masks").iterdir()) == [
        "post_010", "post_post_012", "post_post_013", "pre_pre_011", "pre_pre_013"]
    assert (ev / "before" / "post_010.png").resolve() == (src / "test-pre" / "pre_010.png").resolve()
    union = read_mask(ev / "masks" / "post_010.png")
    assert union.sum() == 32 and union[0, 0] and union[7, 9]
    assert read_mask(ev / "mask_before" / "post_010.png").sum() == 16
    assert (ev / "after" / "post_post_012.png").exists()
    assert (ev / "before" / "pre_pre_011.png").exists()
    fr = _frames(out / "cameras.json")
    assert np.allclose(fr["eval/before/post_010.png"].c2w, _c2w(20), atol=1e-9)
    assert fr["eval/before/post_010.png"].set == "eval_before"


def test_cli_main(tmp_path, capsys):
    _cnerf_tree(tmp_path / "src")
    assert main(["auto", str(tmp_path / "src"), str(tmp_path / "scene"), "--copy"]) == 0
    out = capsys.readouterr().out
    assert "known poses: yes" in out and (tmp_path / "scene" / "cameras.json").exists()
