"""Render stage: the four sequences as EXR + previews + sheets + index, for the tiny scene.

The model is not trained here (that is the fit stage's test): it is built from the tiny
scene's ground truth, one small opaque Gaussian per back-projected pixel of the before views,
so rendered key frames must reproduce the before photos if the poses, intrinsics and EXR
conversions are right.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from gdiff.cameras import save_cameras
from gdiff.errors import ConfigError, SceneError
from gdiff.exr import read_exr, read_frame
from gdiff.interpolate import InterpolateOptions, build_sequence
from gdiff.io import read_image
from gdiff.options import from_config
from gdiff.sequence import (RenderOptions, contact_sheet, load_render_index, psnr,
                            render_sequences, sheet_indices)


def _gt_model(scene, cams, path, stride=3):
    """A static GaussianModel4D from back-projected ground-truth pixels of ``cams``: one small,
    nearly opaque isotropic Gaussian per pixel of a ``stride`` grid."""
    from gdiff.splat.model import GaussianModel4D, save_model

    xyz, rgb, size = [], [], []
    for c in cams:
        r = scene.render(c, "before", supersample=1)
        jj, ii = np.mgrid[0:c.height:stride, 0:c.width:stride]
        z = r["depth"][jj, ii]
        x = (ii + 0.5 - c.cx) / c.fx * z
        y = (jj + 0.5 - c.cy) / c.fy * z
        p = np.stack([x, y, z], -1).reshape(-1, 3)
        xyz.append(p @ c.c2w[:3, :3].T + c.c2w[:3, 3])
        rgb.append(r["rgb"][jj, ii].reshape(-1, 3))
        size.append((0.6 * stride * z / c.fx).reshape(-1))
    xyz, rgb, size = np.concatenate(xyz), np.concatenate(rgb), np.concatenate(size)
    model = GaussianModel4D.from_points(xyz, rgb, sh_degree=0, init_opacity=0.95)
    with torch.no_grad():
        model.splats["scales"].copy_(torch.log(torch.tensor(size, dtype=torch.float32))[:, None]
                                     .repeat(1, 3))
    save_model(model, path, meta={"options": {"background": "black"}})
    return len(xyz)


def _marker_model(points, path, sigma=0.004):
    """Tiny opaque white Gaussians at ``points`` [P, 3] (to locate projections exactly)."""
    from gdiff.splat.model import GaussianModel4D, save_model

    model = GaussianModel4D.from_points(points, np.ones_like(points), sh_degree=0,
                                        init_opacity=0.9)
    with torch.no_grad():
        model.splats["scales"].fill_(math.log(sigma))
    save_model(model, path, meta={"options": {"background": "white"}})


@pytest.fixture(scope="module")
def rendered(synth_tiny_scene, synth_tiny_dir, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("render")
    # every other view keeps the test fast (5 key poses per path)
    before = synth_tiny_scene.cameras("before")[::2]
    after = synth_tiny_scene.cameras("after")[::2]
    save_cameras(tmp / "cameras.json", before + after)
    build_sequence(tmp / "cameras.json", tmp / "poses.json", InterpolateOptions(n=1, max_angle_deg=None, max_step=None))
    _gt_model(synth_tiny_scene, before, tmp / "model.pt")
    summary = render_sequences(tmp / "model.pt", tmp / "poses.json", tmp / "render",
                               RenderOptions(batch=4, sheet_max_frames=6, previews=True),
                               device="cpu",
                               scene_dir=synth_tiny_dir)
    return tmp, summary, before, after


def test_render_writes_all_files_and_index(rendered):
    tmp, summary, before, after = rendered
    out = tmp / "render"
    assert summary["frames"] == {"p1": 5 + 4, "p2": 5 + 4}
    assert (summary["width"], summary["height"]) == (128, 96)
    for p in ("p1", "p2"):
        for t in ("t0", "t1"):
            exr = sorted((out / p / t).glob("*.exr"))
            png = sorted((out / p / t).glob("*.png"))
            assert [f.name for f in exr] == [f"{i:05d}.exr" for i in range(9)]
            assert [f.stem for f in png] == [f.stem for f in exr]
            sheet = read_image(out / p / f"{t}_sheet.png")
            assert sheet.shape[0] > 96 and sheet.shape[1] > 128
    index = json.loads((out / "frames.json").read_text())
    assert (index["width"], index["fx"], index["scale"]) == (128, before[0].fx, 1.0)
    p1 = index["paths"]["p1"]
    assert p1["set"] == "before" and index["paths"]["p2"]["set"] == "after"
    assert [f["image"] for f in p1["frames"] if f["key"]] == [c.image for c in before]
    assert [f["key"] for f in p1["frames"]] == [True, False] * 4 + [True]
    assert p1["t1"]["exr"][3] == "p1/t1/00003.exr" and p1["t0"]["time"] == 0.0
    assert np.allclose(p1["frames"][2]["c2w"], before[1].c2w)
    # the loader resolves files and gives the frame cameras
    idx = load_render_index(out / "frames.json")
    assert idx["paths"]["p2"]["t0"]["exr"][0] == out / "p2" / "t0" / "00000.exr"
    cams = idx["paths"]["p2"]["cameras"]
    assert cams[0].image == after[0].image and np.allclose(cams[0].c2w, after[0].c2w)


def test_render_exr_channels_and_header(rendered):
    tmp, _, before, _ = rendered
    f = tmp / "render" / "p1" / "t0" / "00002.exr"
    ch, header = read_exr(f, with_header=True)
    assert str(header["compression"]).endswith("DWAA_COMPRESSION")  # the default
    assert {k: v.dtype for k, v in ch.items()} == {
        "R": np.float16, "G": np.float16, "B": np.float16, "A": np.float16, "Z": np.float32}
    assert np.allclose(header["worldToCamera"], before[1].w2c, atol=1e-5)
    assert header["gdiff_path"] == "p1" and header["gdiff_time"] == 0.0
    rgb, alpha, depth = read_frame(f)
    assert rgb.shape == (96, 128, 3) and alpha.shape == depth.shape == (96, 128)
    assert alpha.mean() > 0.9  # the closed room covers the whole view
    preview = read_image(tmp / "render" / "p1" / "t0" / "00002.png")
    err = np.abs(preview - np.clip(rgb, 0, 1))  # 8-bit preview vs DWA-compressed colour
    assert err.mean() < 1.0 / 255 and np.quantile(err, 0.999) < 4.0 / 255


def test_render_depth_matches_ground_truth(rendered, synth_tiny_scene):
    tmp, _, before, _ = rendered
    _, alpha, depth = read_frame(tmp / "render" / "p1" / "t0" / "00004.exr")
    gt = synth_tiny_scene.render(before[2], "before", supersample=1)["depth"]
    ok = alpha > 0.95
    ratio = depth / gt
    # front-to-back blending of the blobby test Gaussians biases depth slightly forwards
    assert abs(np.median(ratio[ok]) - 1.0) < 0.06
    # z-depth, not distance along the ray: the ratio is the same at the centre and the corners
    # (distance would be ~17% larger than z in the corners of this 52-degree view)
    H, W = gt.shape
    yy, xx = np.mgrid[0:H, 0:W]
    r = np.hypot((xx - W / 2) / W, (yy - H / 2) / H)
    centre, corner = ok & (r < 0.15), ok & (r > 0.5)
    assert corner.sum() > 100 and centre.sum() > 100
    assert abs(np.median(ratio[corner]) - np.median(ratio[centre])) < 0.04


def test_key_frames_match_photos(rendered, synth_tiny_dir):
    tmp, summary, before, _ = rendered
    index = json.loads((tmp / "render" / "frames.json").read_text())
    assert set(index["key_psnr"]["p1"]) == {c.image for c in before}
    assert summary["key_psnr_p1"] == pytest.approx(np.mean(list(index["key_psnr"]["p1"].values())))
    # every p1 key frame at t0 matches its own before photo better than any other key photo
    # (the blobby test model limits the absolute PSNR to ~16 dB at this size)
    for k, cam in enumerate(before):
        rgb, _, _ = read_frame(tmp / "render" / "p1" / "t0" / f"{2 * k:05d}.exr")
        scores = {c.image: psnr(rgb, read_image(Path(synth_tiny_dir) / c.image)) for c in before}
        own = scores.pop(cam.image)
        assert own > 14.0 and own > max(scores.values()) + 1.0, (cam.image, own, scores)
    # the model is static, so t1 equals t0 on the same pose
    a = read_exr(tmp / "render" / "p1" / "t0" / "00005.exr")
    b = read_exr(tmp / "render" / "p1" / "t1" / "00005.exr")
    assert all(np.array_equal(a[k], b[k]) for k in a)


def test_frames_project_points_exactly(rendered, tmp_path):
    """Tiny Gaussians at known 3D points land where each frame's camera projects them (pixel
    centres at +0.5), on key and interpolated frames of both paths and both times; lossless
    ZIP frames, no previews (the default)."""
    tmp, _, _, _ = rendered
    pts = np.array([[0.3, -0.2, 0.25], [-0.4, 0.1, 0.15], [0.0, 0.35, 0.4], [0.1, 0.05, 0.05]])
    _marker_model(pts, tmp_path / "markers.pt")
    render_sequences(tmp_path / "markers.pt", tmp / "poses.json", tmp_path / "r",
                     RenderOptions(compression="zip", batch=9), device="cpu")
    idx = load_render_index(tmp_path / "r" / "frames.json")
    assert idx["background"] == [1.0, 1.0, 1.0]
    assert not list((tmp_path / "r").rglob("0*.png"))  # previews are off by default
    assert idx["paths"]["p1"]["t0"]["png"] == [] and idx["paths"]["p1"]["t0"]["sheet"].is_file()
    _, header = read_exr(idx["paths"]["p2"]["t1"]["exr"][0], with_header=True)
    assert str(header["compression"]).endswith("ZIP_COMPRESSION")
    checked = 0
    for p in ("p1", "p2"):
        for t in ("t0", "t1"):
            for cam, f in zip(idx["paths"][p]["cameras"], idx["paths"][p][t]["exr"]):
                _, alpha, depth = read_frame(f)
                pc = (cam.w2c[:3, :3] @ pts.T).T + cam.w2c[:3, 3]
                uv = (cam.K @ pc.T).T
                uv = uv[:, :2] / uv[:, 2:]
                gap = np.linalg.norm(uv[:, None] - uv[None], axis=2) + np.eye(len(uv)) * 99
                for (u, v), zc, near in zip(uv, pc[:, 2], gap.min(1)):
                    i, j = int(u), int(v)
                    if near < 8 or not (3 <= i < cam.width - 3 and 3 <= j < cam.height - 3):
                        continue  # another marker in the window, or at the border
                    win = alpha[j - 3:j + 4, i - 3:i + 4].astype(np.float64)
                    yy, xx = np.mgrid[j - 3:j + 4, i - 3:i + 4] + 0.5
                    cu, cv = (win * xx).sum() / win.sum(), (win * yy).sum() / win.sum()
                    assert abs(cu - u) < 0.15 and abs(cv - v) < 0.15, (p, t, f.name, u, v, cu, cv)
                    assert depth[j, i] == pytest.approx(zc, rel=1e-3)
                    checked += 1
    assert checked > 100


def test_render_max_side_scales_cameras(rendered, tmp_path):
    tmp, _, before, _ = rendered
    summary = render_sequences(tmp / "model.pt", tmp / "poses.json", tmp_path / "r",
                               RenderOptions(max_side=64, previews=False, batch=9),
                               device="cpu")
    assert (summary["width"], summary["height"]) == (64, 48)
    index = json.loads((tmp_path / "r" / "frames.json").read_text())
    assert index["scale"] == 0.5 and index["fx"] == pytest.approx(before[0].fx / 2)
    rgb, _, _ = read_frame(tmp_path / "r" / "p2" / "t1" / "00000.exr")
    assert rgb.shape == (48, 64, 3)
    assert not list((tmp_path / "r" / "p2" / "t1").glob("*.png"))


def test_sheet_helpers():
    keys = [i % 5 == 0 for i in range(41)]
    idx = sheet_indices(keys, 12)
    assert len(idx) <= 12 and {0, 5, 10, 40} <= set(idx) and idx == sorted(idx)
    assert sheet_indices(keys[:6], 12) == list(range(6))
    thumbs = [np.full((10, 16, 3), v, np.float32) for v in (0.2, 0.5, 0.8)]
    sheet = contact_sheet(thumbs, ["0", "1", "2"], [True, False, False], columns=2)
    assert sheet.shape[1] == 2 * 16 + 3 * 4 and sheet.dtype == np.uint8
    assert tuple(sheet[4 + 5, 4 + 8]) == (51, 51, 51)  # 0.2 -> 51 inside the first thumbnail
    assert tuple(sheet[4, 4]) == (30, 230, 50)  # key frame border
    assert psnr(thumbs[0], thumbs[0]) == math.inf


def test_render_errors(tmp_path):
    with pytest.raises(ConfigError, match="background"):
        from_config(RenderOptions, {"background": "grey"}, "render")
    with pytest.raises(ConfigError, match="compression must be one of zip, "):
        from_config(RenderOptions, {"compression": "pxr24"}, "render")
    (tmp_path / "poses.json").write_text(json.dumps({"width": 4}))
    with pytest.raises(SceneError, match="paths"):
        render_sequences(tmp_path / "model.pt", tmp_path / "poses.json", tmp_path / "r",
                         device="cpu")


def test_frame_writer_runs_every_write_and_raises_the_first_error():
    from gdiff.sequence import FrameWriter

    done = []
    with FrameWriter(max_pending=2) as w:
        for i in range(7):
            w.submit(done.append, i)
    assert done == list(range(7))  # one thread: in the order submitted

    def boom(i):
        if i == 3:
            raise OSError(f"disk full at {i}")
        done.append(i)

    done.clear()
    w = FrameWriter(max_pending=2)
    with pytest.raises(OSError, match="disk full at 3"):
        with w:
            for i in range(6):
                w.submit(boom, i)
    assert 3 not in done


def test_render_stops_on_a_failed_frame_write_without_an_index(rendered, tmp_path, monkeypatch):
    """A frame that cannot be written (full disk, permissions) fails the stage with that error,
    and frames.json (the stage's completion marker) is not written."""
    import gdiff.sequence as sq

    tmp = rendered[0]
    real = sq.write_frame
    calls = []

    def failing(path, *a, **kw):
        calls.append(path)
        if len(calls) == 5:
            raise OSError(f"{path}: No space left on device")
        return real(path, *a, **kw)

    monkeypatch.setattr(sq, "write_frame", failing)
    with pytest.raises(OSError, match="No space left on device"):
        render_sequences(tmp / "model.pt", tmp / "poses.json", tmp_path / "r",
                         RenderOptions(batch=2, previews=False), device="cpu")
    assert not (tmp_path / "r" / "frames.json").exists()
