"""Evaluate stage and baselines on small image pairs with known changes."""

import json
import math
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from gdiff import baselines as B
from gdiff import evaluate as E
from gdiff.cameras import Camera, look_at, save_cameras
from gdiff.errors import SceneError
from gdiff.io import read_image, read_mask, write_image, write_mask

H, W = 48, 64


def _texture(seed):
    rng = np.random.default_rng(seed)
    base = rng.uniform(0.2, 0.8, (H // 8, W // 8, 3)).astype(np.float32)
    img = np.kron(base, np.ones((8, 8, 1), np.float32))  # blocky texture
    return np.clip(img + rng.normal(0, 0.01, img.shape).astype(np.float32), 0, 1)


def _pair(seed, box):
    """Before: textured background; after: a flat-coloured object added in ``box``."""
    before = _texture(seed)
    after = before.copy()
    x0, y0, x1, y1 = box
    after[y0:y1, x0:x1] = (0.95, 0.1, 0.1)
    after = np.clip(after + np.random.default_rng(seed + 1).normal(0, 0.01, after.shape), 0, 1)
    mask = np.zeros((H, W), bool)
    mask[y0:y1, x0:x1] = True
    return before, after.astype(np.float32), mask


def _scene(tmp_path, post_only=()):
    root = tmp_path / "scene"
    boxes = {"000": (8, 8, 24, 20), "001": (30, 20, 50, 40), "002": (4, 30, 14, 44)}
    cams = []
    for i, (name, box) in enumerate(boxes.items()):
        before, after, mask = _pair(i, box)
        if name not in post_only:
            write_image(root / "eval" / "before" / f"{name}.png", before)
        write_image(root / "eval" / "after" / f"{name}.png", after)
        write_mask(root / "eval" / "masks" / f"{name}.png", mask)
        # cameras at twice the eval resolution: the stage must scale them to the masks
        for st in ("eval_before", "eval_after"):
            cams.append(Camera(2 * W, 2 * H, 100.0, 100.0, W, H,
                               look_at([i, -3.0, 1.0], [0, 0, 0]),
                               image=f"eval/{st[5:]}/{name}.png", set=st,
                               time=0 if st == "eval_before" else 1))
    save_cameras(root / "cameras.json", cams)
    return root, boxes


def test_pixel_diff_finds_added_object():
    before, after, mask = _pair(3, (10, 10, 30, 26))
    pred = B.pixel_diff(before, after, blur_sigma=1.0, min_threshold=0.05)
    from gdiff.metrics import score_view

    s, _ = score_view(pred.mask, mask, pred.prob)
    assert s["F1"] > 0.85 and s["box_TP"] == 1 and s["box_FP"] == 0
    # identical images: the floor keeps Otsu from splitting noise into "change"
    same = B.pixel_diff(before, before + 0.004, blur_sigma=1.0)
    assert not same.mask.any()
    with pytest.raises(ValueError, match="differ in size"):
        B.pixel_diff(before, after[:-1])


def test_find_eval_views_matches_cameras_and_checks_layout(tmp_path):
    root, boxes = _scene(tmp_path)
    views = E.find_eval_views(root, root / "cameras.json")
    assert [v.name for v in views] == sorted(boxes)
    v = views[1]
    assert v.before.name == "001.png" and v.after.parent.name == "after"
    assert v.camera.set == "eval_after"
    cam = v.camera_at_gt_size()
    assert (cam.width, cam.height) == (W, H) and cam.fx == pytest.approx(50.0)
    # an eval image without a mask is a user error naming the file
    write_image(root / "eval" / "after" / "009.png", np.zeros((H, W, 3)))
    with pytest.raises(SceneError, match="009"):
        E.find_eval_views(root)


def test_evaluate_scene_side_by_side(tmp_path):
    root, boxes = _scene(tmp_path)
    gts = {n: read_mask(root / "eval" / "masks" / f"{n}.png") for n in boxes}

    def fake_detect(rgb0, rgb1, depth0=None, depth1=None):
        # stands in for segment + track + compare: the changed object is seen only after
        d = np.abs(rgb1 - rgb0).max(axis=2) > 0.3
        return np.zeros_like(d), d

    seen_cams = []

    def fake_change_map(pmodel, camera, t=None):
        seen_cams.append(camera)
        name = pmodel[round(camera.center[0])]
        m = gts[name].copy()
        m[:, :2] = True  # a thin false strip
        return {"mask": m, "prob": np.where(m, 0.9, 0.1)}

    methods = {"pixel_diff": B.pixel_diff_method(blur_sigma=1.0),
               "idcompare": B.idcompare_method(detect=fake_detect),
               "partition": B.partition_method(dict(enumerate(sorted(boxes))),
                                               render_change_map=fake_change_map)}
    out = tmp_path / "results" / "scene" / "eval"
    df = E.evaluate_scene(root, root / "cameras.json", out, "scene", methods, E.EvalOptions())
    assert list(df.columns) == E.METRIC_COLUMNS
    assert len(df) == 9 and set(df["method"]) == set(methods)
    assert all((c.width, c.height) == (W, H) for c in seen_cams)
    part = df[df["method"] == "partition"]
    assert (part["R"] == 1.0).all() and (part["P"] < 1.0).all()
    assert (part["box_TP"] == 1).all()
    assert (df[df["method"] == "idcompare"]["F1"] > 0.9).all()
    back = pd.read_csv(out / "metrics.csv")
    assert back[["TP", "FP", "FN"]].to_numpy().tolist() == df[["TP", "FP", "FN"]].to_numpy().tolist()
    summ = pd.read_csv(out / "scene_summary.csv")
    assert set(summ["method"]) == set(methods) and (summ["n_views"] == 3).all()
    boxes_csv = pd.read_csv(out / "boxes.csv")
    assert ((boxes_csv["kind"] == "gt").sum()) == 9  # 3 GT boxes x 3 methods
    m = read_mask(out / "maps" / "partition" / "000.png")
    assert m[:, :2].all()
    ov = read_image(out / "overlays" / "001.png")
    assert ov.shape == (3 * H, 4 * W, 3)
    # TP pixels are green in the error panel of the partition row (third row, fourth panel)
    x0, y0, x1, y1 = boxes["001"]
    cell = ov[2 * H + (y0 + y1) // 2, 3 * W + (x0 + x1) // 2]
    assert cell[1] > 0.6 and cell[0] < 0.3


def test_post_only_views_use_renderer_or_are_skipped(tmp_path):
    root, boxes = _scene(tmp_path, post_only=("001",))
    opts = E.EvalOptions(methods=["pixel_diff"], overlays=False)
    df = E.evaluate_scene(root, root / "cameras.json", tmp_path / "a", "s",
                          E.build_methods(opts), opts)
    assert sorted(df["view"]) == ["000", "002"]
    rendered = []

    def render(camera, t):
        rendered.append((camera.width, t))
        return _pair(1, boxes["001"])[0]  # the true before state of view 001

    df = E.evaluate_scene(root, root / "cameras.json", tmp_path / "b", "s",
                          E.build_methods(opts, render=render), opts)
    assert sorted(df["view"]) == ["000", "001", "002"]
    assert rendered == [(W, 0.0)]
    assert df.set_index("view").loc["001", "F1"] > 0.85


def test_options_are_checked():
    with pytest.raises(ValueError, match="unknown"):
        E.EvalOptions(methods=["pixel_diff", "magic"])
    with pytest.raises(Exception, match="partition model"):
        E.build_methods(E.EvalOptions())


def test_idcompare_uses_model_depth_to_ignore_a_moved_shadow(tmp_path):
    """The eval photos have no depth; with the model's depth at the eval camera a darkened
    (shadowed) region whose depth did not change is not a change, while the added object, nearer
    at t=1, is."""
    root, boxes = _scene(tmp_path)
    view = E.find_eval_views(root, root / "cameras.json")[1]
    before = view.read_image(0)
    after = view.read_image(1).copy()
    after[0:16, 0:24] *= 0.5  # a shadow cast on the unchanged background
    write_image(root / "eval" / "after" / "001.png", after)
    x0, y0, x1, y1 = boxes["001"]
    calls = []

    def depth(cam, t):
        calls.append(((cam.width, cam.height), t))
        z = np.full((cam.height, cam.width), 4.0, np.float32)
        if t == 1.0:
            z[y0:y1, x0:x1] = 3.0  # the added object stands in front of the wall
        return z

    gt = view.read_gt()
    from gdiff.metrics import score_view

    with_depth = B.idcompare_method(depth=depth)(view)
    assert sorted(calls) == [((W, H), 0.0), ((W, H), 1.0)]
    s, _ = score_view(with_depth.mask, gt)
    assert s["F1"] > 0.9
    assert not with_depth.mask[0:16, 0:24].any()
    np.testing.assert_array_less(0, before.sum())  # the view was read, not skipped
    opts = E.EvalOptions(methods=["idcompare"], idcompare_depth=False)
    assert E.build_methods(opts, depth=depth)["idcompare"](view) is not None
    assert len(calls) == 2  # idcompare_depth=False: the depth renderer is not used
    on = E.EvalOptions(methods=["idcompare"], idcompare_depth=True)
    E.build_methods(on, depth=depth)["idcompare"](view)
    assert len(calls) == 4  # idcompare_depth=True: rendered at t=0 and t=1


def test_object_recall_from_before_and_after_masks(tmp_path):
    """A moved object is two object views (its place before, its place after); a method that
    finds only the new place finds one of two. Without mask_before/mask_after the change mask's
    regions are the objects."""
    root, boxes = _scene(tmp_path)
    before_box = (40, 4, 56, 16)  # its place before (after: boxes["000"])
    mb = np.zeros((H, W), bool)
    mb[before_box[1]:before_box[3], before_box[0]:before_box[2]] = True
    ma = read_mask(root / "eval" / "masks" / "000.png")
    write_mask(root / "eval" / "mask_before" / "000.png", mb)
    write_mask(root / "eval" / "mask_after" / "000.png", ma)
    write_mask(root / "eval" / "masks" / "000.png", mb | ma)

    def only_after(view):  # predicts the ground truth of the after state only
        if view.mask_after is not None:
            return read_mask(view.mask_after)
        return view.read_gt()

    opts = E.EvalOptions(methods=["pixel_diff"], overlays=False)
    out = tmp_path / "out"
    df = E.evaluate_scene(root, None, out, "s", {"pixel_diff": only_after}, opts)
    v = df.set_index("view")
    assert (v.loc["000", "obj_N"], v.loc["000", "obj_found"]) == (2, 1)
    assert (v.loc["001", "obj_N"], v.loc["001", "obj_found"]) == (1, 1)
    summ = pd.read_csv(out / "scene_summary.csv").iloc[0]
    assert summ["obj_R_pooled"] == pytest.approx(3 / 4)
    back = pd.read_csv(out / "metrics.csv")
    assert back["obj_N"].tolist() == [2, 1, 1]
    # an object mask of another size than the change mask is named
    write_mask(root / "eval" / "mask_after" / "000.png", np.zeros((H // 2, W // 2), bool))
    with pytest.raises(SceneError, match="mask_after/000.png"):
        E.evaluate_scene(root, None, tmp_path / "o2", "s", {"pixel_diff": only_after}, opts)


def test_box_ground_truth_on_eval_views_and_training_images(tmp_path, caplog):
    """eval/boxes.json in the ObChange layout: boxes of an eval view are scored beside its mask;
    boxes of a training image (after/v00.png) make a box view where only the partition is
    rendered, at that image's camera (at the image's size), and the others are skipped."""

    root, boxes = _scene(tmp_path)
    from gdiff.cameras import load_cameras

    cams = load_cameras(root / "cameras.json")
    # a training image at half the eval size, camera given at the eval size
    write_image(root / "after" / "v00.png", _texture(7)[::2, ::2])
    write_image(root / "before" / "v00.png", _texture(7)[::2, ::2])
    cams.append(Camera(2 * W, 2 * H, 100.0, 100.0, W, H, look_at([9, -3.0, 1.0], [0, 0, 0]),
                       image="after/v00.png", set="after", time=1))
    # a training image where nothing changed: an empty list, so every mark there is far
    write_image(root / "after" / "v01.png", _texture(8)[::2, ::2])
    cams.append(Camera(2 * W, 2 * H, 100.0, 100.0, W, H, look_at([8, -3.0, 1.0], [0, 0, 0]),
                       image="after/v01.png", set="after", time=1))
    save_cameras(root / "cameras.json", cams)
    (root / "eval" / "boxes.json").write_text(json.dumps({"note": "pixels", "views": {
        "001.png": {"boxes_xyxy_px": [list(boxes["001"]), [0, 0, 6, 6]]},
        "v00.png": {"after_src": "x.png", "boxes_xyxy_px": [[2, 2, 12, 10], [20, 14, 30, 22]]},
        "v01.png": {"boxes_xyxy_px": []}}}))
    seen = []

    def change_map(pmodel, camera, t=None):
        seen.append((camera.width, camera.height))
        if round(camera.center[0]) == 9:  # the training view: the first box only, plus a
            m = np.zeros((camera.height, camera.width), bool)  # far false alarm
            m[3:9, 3:11] = True
            m[0:4, 28:32] = True
            return {"mask": m}
        if round(camera.center[0]) == 8:  # the view without change: 5 x 3 px marked
            m = np.zeros((camera.height, camera.width), bool)
            m[10:13, 2:7] = True
            return {"mask": m}
        name = pmodel[round(camera.center[0])]
        return {"mask": read_mask(root / "eval" / "masks" / f"{name}.png")}

    methods = {"pixel_diff": B.pixel_diff_method(blur_sigma=1.0),
               "partition": B.partition_method(dict(enumerate(sorted(boxes))),
                                               render_change_map=change_map)}
    opts = E.EvalOptions(box_margin=4.0)
    out = tmp_path / "out"
    # the compare stage's judged map at the training image (at the render size, W x H here:
    # twice the image's): it judged the left half only
    jm = np.full((H, W), 64, np.uint8)
    jm[:, : W // 2] = 128
    write_image(tmp_path / "res" / "change" / "p2" / "judged" / "00003.png", jm)
    pd.DataFrame([dict(path="p2", frame=3, image="after/v00.png", set="after", time=1,
                       mask_t0="x", mask_t1="x", mask_union="x",
                       judged="change/p2/judged/00003.png")]).to_csv(
        tmp_path / "res" / "change" / "keyframes.csv", index=False)
    judged = E.judged_maps(tmp_path / "res" / "change" / "keyframes.csv")
    assert judged == {"after/v00": tmp_path / "res" / "change" / "p2" / "judged" / "00003.png"}
    with caplog.at_level("INFO", logger="gdiff.evaluate"):
        df = E.evaluate_scene(root, root / "cameras.json", out, "s", methods, opts,
                              judged=judged)
    # the missed box the compare stage never judged is named in the log
    assert re.search(r"s partition: 1 of the missed boxes lie mostly where the compare stage "
                     r"could not judge.*after/v00 box 1", caplog.text)
    assert (W // 2, H // 2) in seen  # rendered at the training image's size
    bv = df[df["view"] == "after/v00"]
    assert list(bv["method"]) == ["partition"]  # pixel_diff needs an eval pair: skipped
    r = bv.iloc[0]
    assert (r["gtbox_N"], r["gtbox_found"]) == (2, 1) and math.isnan(r["F1"])
    # margin 4 px at the image's size (32 px wide) = 2 px: the 4x4 block at x 28..32 is far
    assert r["far_FP"] == 16 and r["far_frac"] == pytest.approx(16 / (W // 2 * H // 2))
    nv = df[(df["view"] == "after/v01") & (df["method"] == "partition")].iloc[0]
    assert (nv["gtbox_N"], nv["gtbox_found"], nv["far_FP"]) == (0, 0, 15)
    ev = df[(df["view"] == "001") & (df["method"] == "partition")].iloc[0]
    assert (ev["gtbox_N"], ev["gtbox_found"]) == (2, 1) and ev["F1"] == 1.0
    assert df[df["view"] == "000"]["gtbox_N"].isna().all()
    summ = pd.read_csv(out / "scene_summary.csv").set_index("method")
    assert summ.loc["partition", "gtbox_R_pooled"] == pytest.approx(2 / 4)
    # boxes.csv: every box of boxes.json per view and method, with its core's marked share
    bx = pd.read_csv(out / "boxes.csv")
    gb = bx[(bx["kind"] == "gt_box") & (bx["view"] == "after/v00")]
    assert list(gb["method"]) == ["partition", "partition"]
    assert list(gb["matched"]) == [True, False]
    # box 1's core (x 4.5..9.5, y 4..8) lies in the marked block (x 3..11, y 3..9); box 2's
    # is not marked at all
    assert list(gb["core"]) == [1.0, 0.0]
    # box 1 (x 2..12 of 32) where the compare stage judged, box 2 (x 20..30) where it did not;
    # the eval view has no judged map
    assert list(gb["judged"]) == [1.0, 0.0]
    assert bx.loc[(bx["kind"] == "gt_box") & (bx["view"] == "001"), "judged"].isna().all()
    assert len(bx[(bx["kind"] == "gt_box") & (bx["view"] == "001")]) == 2 * len(methods)
    assert (bx["kind"] == "gt_box").sum() == 2 + 2 * len(methods)
    assert bx.loc[bx["kind"] != "gt_box", "core"].isna().all()
    assert (out / "overlays" / "after" / "v00.png").is_file()
    # a malformed box and an unknown image are named
    (root / "eval" / "boxes.json").write_text(json.dumps({"001": [[5, 5, 2, 9]]}))
    with pytest.raises(SceneError, match="'001'"):
        E.find_eval_views(root)
    (root / "eval" / "boxes.json").write_text(json.dumps({"after/zz.png": [[1, 1, 2, 2]]}))
    with pytest.raises(SceneError, match="zz.png"):
        E.find_eval_views(root)


def test_box_only_scene_validates(tmp_path):
    """A real capture with boxes only (no eval pairs): eval/boxes.json may be all of eval/."""
    from gdiff.scene import validate_scene

    root = tmp_path / "s"
    for d in ("before", "after"):
        for i in range(3):
            write_image(root / d / f"{i:03d}.png", _texture(i))
    (root / "eval").mkdir()
    (root / "eval" / "boxes.json").write_text('{"000.png": [[1, 2, 10, 12]]}')
    assert validate_scene(root)["eval_views"] == []
    views = E.find_eval_views(root)
    assert [v.name for v in views] == ["after/000"] and views[0].mask is None
    assert views[0].box_size == (W, H) and views[0].shape() == (H, W)
    # a dataset's file copied whole for a scene made of some of its views: an entry without
    # boxes for a photo left out is skipped, one with boxes stops the scene's check at once
    # (not at the end of the run, when evaluate reads it)
    (root / "eval" / "boxes.json").write_text(json.dumps({"views": {
        "000.png": {"boxes_xyxy_px": [[1, 2, 10, 12]]}, "007.png": {"boxes_xyxy_px": []}}}))
    validate_scene(root)
    assert [v.name for v in E.find_eval_views(root)] == ["after/000"]
    (root / "eval" / "boxes.json").write_text(json.dumps({"views": {
        "000.png": {"boxes_xyxy_px": [[1, 2, 10, 12]]},
        "007.png": {"boxes_xyxy_px": [[1, 1, 5, 5]]}}}))
    with pytest.raises(SceneError, match=r"boxes.json: entry '007.png' has 1 box\(es\)"):
        validate_scene(root)


def test_render_quality_psnr_at_eval_views(tmp_path):
    root, boxes = _scene(tmp_path, post_only=("002",))
    views = E.find_eval_views(root, root / "cameras.json")
    seen = []

    def render(camera, t):  # the true image at t=1, the true image + 0.1 at t=0
        seen.append((camera.width, camera.height, t))
        v = views[round(camera.center[0])]
        return v.read_image(1) if t == 1.0 else np.clip(v.read_image(0) + 0.1, 0, 1)

    q = E.render_quality(views, render)
    assert len(q) == 5 and set(seen) >= {(W, H, 0.0), (W, H, 1.0)}  # 002 has no before image
    assert (q[q["time"] == 1]["psnr"] > 90).all()
    t0 = q[q["time"] == 0]["psnr"]
    assert t0.between(19.0, 20.01).all()  # +0.1 everywhere (a little less where clipped)


def test_render_diff_scores_the_fitted_model_at_any_camera(tmp_path):
    """render_diff compares the model's own renders at t=0 and t=1 at the eval camera: scored at
    eval views and, as a camera method, at training images with boxes; without a renderer the
    method is left out."""

    root, boxes = _scene(tmp_path)
    from gdiff.cameras import load_cameras

    cams = load_cameras(root / "cameras.json")
    write_image(root / "after" / "v00.png", _texture(7))
    write_image(root / "before" / "v00.png", _texture(7))
    cams.append(Camera(W, H, 50.0, 50.0, W / 2, H / 2, look_at([9, -3.0, 1.0], [0, 0, 0]),
                       image="after/v00.png", set="after", time=1))
    save_cameras(root / "cameras.json", cams)
    (root / "eval" / "boxes.json").write_text(json.dumps({"after/v00.png": [[20, 8, 40, 24]]}))
    names = sorted(boxes)
    rendered = []

    def render(camera, t):
        """The scene's true state at time t, as a perfect fit would render it."""
        rendered.append((round(camera.center[0]), t, camera.width))
        i = round(camera.center[0])
        if i == 9:  # the training image: an object added in its box at t=1
            img = _texture(7)
            if t == 1.0:
                img = img.copy()
                img[8:24, 20:40] = (0.1, 0.2, 0.95)
            return img
        return _pair(i, boxes[names[i]])[int(t)]

    opts = E.EvalOptions(methods=["pixel_diff", "render_diff"], overlays=False)
    assert list(E.build_methods(opts)) == ["pixel_diff"]  # no model to render: left out
    methods = E.build_methods(opts, render=render)
    df = E.evaluate_scene(root, root / "cameras.json", tmp_path / "out", "s", methods, opts)
    rd = df[df["method"] == "render_diff"].set_index("view")
    assert sorted(rd.index) == ["000", "001", "002", "after/v00"]
    assert (rd.loc[["000", "001", "002"], "F1"] > 0.85).all()
    assert rd.loc["after/v00", "gtbox_found"] == 1 and rd.loc["after/v00", "far_frac"] < 0.01
    assert {(x, t) for x, t, _ in rendered} >= {(0, 0.0), (0, 1.0), (9, 0.0), (9, 1.0)}
    assert all(w == W for _, _, w in rendered)  # at the ground truth's size
    assert list(df[df["view"] == "after/v00"]["method"]) == ["render_diff"]


def test_model_renderer_renders_each_camera_and_time_once(monkeypatch):
    """The evaluate rule asks for each eval view twice (render_diff, then the fit's quality):
    the second ask returns the kept render, read-only; another time or camera renders again,
    and nothing is kept beyond the budget."""
    import torch

    import gdiff.splat.render as R
    from gdiff.splat.model import GaussianModel4D

    model = GaussianModel4D(1, sh_degree=0, deform=None)
    with torch.no_grad():
        model.splats["means"].zero_()
        model.splats["scales"].fill_(math.log(0.1))
    calls = []
    real = R.render

    def counting(*a, **k):
        calls.append(a[2])
        return real(*a, **k)

    monkeypatch.setattr(R, "render", counting)
    cam = Camera(40, 30, 40.0, 40.0, 20, 15, look_at([0, -2.0, 0], [0, 0, 0]))
    render = E.model_renderer(model)
    a = render(cam, 0.0)
    assert render(cam, 0.0) is a and not a.flags.writeable
    render(cam, 1.0)
    render(Camera(40, 30, 40.0, 40.0, 20, 15, look_at([0, -2.5, 0], [0, 0, 0])), 0.0)
    assert calls == [0.0, 1.0, 0.0]
    tight = E.model_renderer(model, keep_mb=0.0)
    tight(cam, 0.0)
    tight(cam, 0.0)
    assert calls == [0.0, 1.0, 0.0, 0.0, 0.0]


def test_shipped_kitchen_boxes_read():
    """benchmarks/data/obchange_kitchen_boxes.json (the robot kitchen's hand-drawn boxes) reads
    as box ground truth: six after views, the three without change as empty lists, 8 boxes
    inside the 640 x 480 photos."""
    b = E.read_boxes(Path(__file__).resolve().parents[1] / "benchmarks" / "data"
                     / "obchange_kitchen_boxes.json")
    assert sorted(b) == [f"after/v{i:02d}.png" for i in range(6)]
    assert [len(b[f"after/v{i:02d}.png"]) for i in range(6)] == [0, 0, 0, 2, 3, 3]
    allb = np.concatenate([v for v in b.values() if len(v)])
    assert (allb[:, :2] >= 0).all() and (allb[:, 2] <= 640).all() and (allb[:, 3] <= 480).all()
