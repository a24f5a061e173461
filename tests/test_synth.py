"""Procedural scenes: determinism, folder layout, exact masks, shadows, lighting change,
projection/depth conventions, cameras and the CLI."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from gdiff import synth
from gdiff.errors import ConfigError, GdiffError
from gdiff.io import read_mask
from gdiff.options import from_config

# small variants of the presets (same geometry and changes, fewer/smaller images)
MICRO = dataclasses.replace(synth.PRESETS["tiny"], width=64, height=48, n_before=3, n_after=3,
                            n_eval=2)
LIGHT = dataclasses.replace(synth.PRESETS["lightchange"], width=96, height=72, n_before=2,
                            n_after=2, n_eval=3, supersample=1)


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file()}


def _luma(rgb):
    return rgb @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)


# --------------------------------------------------------------------------------------------
def test_determinism(tmp_path):
    a = _files(synth.make_scene(tmp_path / "a", MICRO, seed=3))
    b = _files(synth.make_scene(tmp_path / "b", MICRO, seed=3))
    c = _files(synth.make_scene(tmp_path / "c", MICRO, seed=4))
    for d in (a, b, c):
        d.pop("timing.json")
    a["meta.json"] = a["meta.json"].replace(b'"scene": "a"', b'"scene": "b"')
    a["gt_cameras.json"] = a["gt_cameras.json"].replace(b'"scene": "a"', b'"scene": "b"')
    assert a.keys() == b.keys() == c.keys()
    assert all(a[k] == b[k] for k in a), [k for k in a if a[k] != b[k]]
    assert a["before/000.png"] != c["before/000.png"]
    assert json.loads(a["meta.json"])["objects"] != json.loads(c["meta.json"])["objects"]


def test_folder_layout_and_schema(synth_tiny_dir):
    root = synth_tiny_dir
    p = synth.PRESETS["tiny"]
    expect = {f"{d}/{i:03d}.png" for d, n in (("before", p.n_before), ("after", p.n_after))
              for i in range(n)}
    expect |= {f"eval/{d}/{i:03d}.png" for d in ("before", "after", "masks", "mask_before",
                                                 "mask_after") for i in range(p.n_eval)}
    expect |= {"gt_cameras.json", "meta.json", "timing.json"}
    assert set(_files(root)) == expect
    assert not [q for q in root.parent.iterdir() if q.name.startswith(".")]  # no temp folders

    img = cv2.imread(str(root / "before/000.png"), cv2.IMREAD_UNCHANGED)
    assert img.dtype == np.uint8 and img.shape == (p.height, p.width, 3)
    m = cv2.imread(str(root / "eval/masks/000.png"), cv2.IMREAD_UNCHANGED)
    assert m.dtype == np.uint8 and m.shape == (p.height, p.width)
    assert set(np.unique(m)) <= {0, 255}

    gt = json.loads((root / "gt_cameras.json").read_text())
    assert set(gt) == {"scene", "convention", "intrinsics", "frames", "eval_views"}
    intr = gt["intrinsics"]
    assert {"width", "height", "fx", "fy", "cx", "cy", "K"} <= set(intr)
    assert (intr["width"], intr["height"]) == (p.width, p.height)
    assert np.allclose(intr["K"], [[intr["fx"], 0, intr["cx"]], [0, intr["fy"], intr["cy"]],
                                   [0, 0, 1]])
    frames = gt["frames"]
    assert len(frames) == p.n_before + p.n_after + 2 * p.n_eval
    for fr in frames:
        assert {"file", "split", "state", "index", "c2w"} <= set(fr)
        assert (root / fr["file"]).is_file()
        assert fr["split"] in ("train", "eval") and fr["state"] in ("before", "after")
        R = np.asarray(fr["c2w"])[:3, :3]
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-9) and np.linalg.det(R) > 0
        if fr["split"] == "train":
            assert fr["file"] == f"{fr['state']}/{fr['index']:03d}.png"
        else:
            assert fr["file"] == f"eval/{fr['state']}/{fr['index']:03d}.png"
            assert (root / fr["mask"]).is_file()
    assert [v["index"] for v in gt["eval_views"]] == list(range(p.n_eval))

    meta = json.loads((root / "meta.json").read_text())
    assert meta["seed"] == 0 and meta["preset"] == "tiny"
    assert sorted(c["type"] for c in meta["changes"]) == ["added", "removed"]
    assert {"before", "after"} <= set(meta["lighting"])
    assert meta["lighting"]["before"]["lights"][0]["type"] == "SUN"
    for v in meta["gt_mask"]["per_view"]:  # counts match the files
        i = v["index"]
        assert v["changed_pixels"] == read_mask(root / f"eval/masks/{i:03d}.png").sum()
        assert v["before_pixels"] == read_mask(root / f"eval/mask_before/{i:03d}.png").sum()
        assert v["after_pixels"] == read_mask(root / f"eval/mask_after/{i:03d}.png").sum()
    assert sum(v["changed_pixels"] for v in meta["gt_mask"]["per_view"]) > 0


def test_masks_are_changed_objects_visible_pixels(synth_tiny_dir, synth_tiny_scene):
    scene = synth_tiny_scene
    kinds = scene.change_types
    gone = [i for i, k in kinds.items() if k in ("removed", "moved")]
    come = [i for i, k in kinds.items() if k in ("added", "moved")]
    assert gone and come
    for i, cam in enumerate(scene.cameras("eval")):
        rb = scene.render(cam, "before", supersample=1)
        ra = scene.render(cam, "after", supersample=1)
        mb = np.isin(rb["ids"], gone)
        ma = np.isin(ra["ids"], come)
        disk_b = read_mask(synth_tiny_dir / f"eval/mask_before/{i:03d}.png")
        disk_a = read_mask(synth_tiny_dir / f"eval/mask_after/{i:03d}.png")
        disk = read_mask(synth_tiny_dir / f"eval/masks/{i:03d}.png")
        assert np.array_equal(disk_b, mb) and np.array_equal(disk_a, ma)
        assert np.array_equal(disk, mb | ma)
        assert np.array_equal(rb["changed"], mb) and np.array_equal(ra["changed"], ma)
        # unchanged pixels show the same thing in both states
        same = ~(mb | ma)
        assert np.array_equal(rb["ids"][same], ra["ids"][same])


def test_render_outputs(synth_tiny_scene):
    scene = synth_tiny_scene
    cam = scene.cameras("before")[0]
    r = scene.render(cam, "before")
    H, W = cam.height, cam.width
    assert r["rgb"].dtype == np.float32 and r["rgb"].shape == (H, W, 3)
    assert 0.0 <= r["rgb"].min() and r["rgb"].max() <= 1.0 and r["rgb"].std() > 0.05
    assert r["depth"].dtype == np.float32 and r["depth"].shape == (H, W)
    assert np.isfinite(r["depth"]).all() and r["depth"].min() > 0  # closed room: every ray hits
    assert r["normal"].dtype == np.float32 and r["normal"].shape == (H, W, 3)
    assert np.allclose(np.linalg.norm(r["normal"], axis=2), 1.0, atol=1e-5)
    assert r["ids"].dtype == np.int32 and r["changed"].dtype == bool
    present = {o.id for o in scene.objects_in("before")}
    assert set(np.unique(r["ids"])) - {0} <= present
    # supersampling only changes the colour, never the ground truth
    r1 = scene.render(cam, "before", supersample=1)
    assert np.array_equal(r1["ids"], r["ids"]) and np.array_equal(r1["depth"], r["depth"])
    assert not np.array_equal(r1["rgb"], r["rgb"])
    with pytest.raises(ValueError):
        scene.render(cam, "later")


def test_projection_and_depth(synth_tiny_scene):
    """Project each object's centre: the pixel shows that object, or something nearer.
    Unprojected depths lie on the object seen (inside its box) or on the floor."""
    scene = synth_tiny_scene
    hits = checks = 0
    for split, state in (("eval", "before"), ("eval", "after"), ("before", "before")):
        for cam in scene.cameras(split)[:3]:
            r = scene.render(cam, state, supersample=1)
            for obj in scene.objects_in(state):
                X = scene.object_center(obj, state)
                xc = cam.w2c[:3, :3] @ X + cam.w2c[:3, 3]
                u, v = (cam.K @ xc)[:2] / xc[2]
                i, j = int(np.floor(u)), int(np.floor(v))
                if not (0 <= i < cam.width and 0 <= j < cam.height):
                    continue
                checks += 1
                if r["ids"][j, i] == obj.id:
                    hits += 1
                else:
                    assert r["depth"][j, i] < xc[2] - 1e-3
            # unproject the pixel centres with the z-depth
            H, W = cam.height, cam.width
            jj, ii = np.mgrid[0:H, 0:W] + 0.5
            xyz = np.stack([(ii - cam.cx) / cam.fx, (jj - cam.cy) / cam.fy, np.ones_like(ii)], -1)
            X = (xyz * r["depth"][..., None]) @ cam.c2w[:3, :3].T + cam.c2w[:3, 3]
            for obj in scene.objects_in(state):
                lo, hi = scene.object_bbox(obj, state)
                pts = X[r["ids"] == obj.id]
                assert (pts >= lo - 1e-6).all() and (pts <= hi + 1e-6).all()
            floor = (r["ids"] == 0) & (r["normal"][..., 2] > 0.999) & (X[..., 2] < 0.01)
            assert floor.sum() > 50 and np.abs(X[floor, 2]).max() < 1e-6
    assert checks >= 10 and hits >= 0.6 * checks


def test_cast_shadows():
    scene = synth.build_scene(LIGHT, 0)
    found = 0
    for cam in scene.cameras("eval"):
        r = scene.render(cam, "after")
        r0 = scene.render(cam, "after", shadows=False)
        sh = r["shadow"]
        assert sh.sum() > 20
        assert not r0["shadow"].any()
        lum, lum0 = _luma(r["rgb"]), _luma(r0["rgb"])
        # a shadowed pixel is much darker than the same surface lit; elsewhere nothing changes
        assert np.median(lum[sh] / np.maximum(lum0[sh], 1e-3)) < 0.7
        far = cv2.dilate(sh.astype(np.uint8), np.ones((5, 5), np.uint8)) == 0
        assert np.abs(lum[far] - lum0[far]).max() < 1e-6
        # the analytic shadow of each object's centre, where visible, is in the shadow mask
        ld = scene.lighting["after"].suns[0].direction
        for obj in scene.objects_in("after"):
            c = scene.object_center(obj, "after")
            P = c - ld * (c[2] - scene.preset.table_height) / ld[2]
            if np.abs(P[:2]).max() > min(scene.preset.table_half_size) - 0.02:
                continue
            xc = cam.w2c[:3, :3] @ P + cam.w2c[:3, 3]
            u, v = (cam.K @ xc)[:2] / xc[2]
            i, j = int(np.floor(u)), int(np.floor(v))
            if not (0 <= i < cam.width and 0 <= j < cam.height):
                continue
            if r["ids"][j, i] != 0 or abs(r["depth"][j, i] - xc[2]) > 0.02:
                continue  # hidden behind something
            found += 1
            assert sh[j, i] and lum[j, i] < 0.7 * lum0[j, i]
    assert found >= 2


def test_lighting_change_keeps_ids():
    scene = synth.build_scene(LIGHT, 0)
    assert scene.lighting["before"] != scene.lighting["after"]
    types = sorted(c["type"] for c in scene.changes)
    assert types == ["moved", "replaced"]
    rep = next(c for c in scene.changes if c["type"] == "replaced")
    assert rep["new_kind"] != rep["kind"] and rep["new_id"] != rep["id"]
    assert {rep["id"], rep["new_id"]} <= set(scene.changed_ids)
    diffs = []
    for cam in scene.cameras("eval"):
        rb = scene.render(cam, "before")
        ra = scene.render(cam, "after")
        same = ~(rb["changed"] | ra["changed"])
        assert np.array_equal(rb["ids"][same], ra["ids"][same])
        bg = same & (rb["ids"] == 0)
        diffs.append(abs(_luma(rb["rgb"])[bg].mean() - _luma(ra["rgb"])[bg].mean()))
        # the light moved: shadows fall elsewhere
        assert (rb["shadow"] != ra["shadow"]).mean() > 0.01
    assert min(diffs) > 0.03


def test_moved_object_keeps_its_id():
    scene = synth.build_scene(dataclasses.replace(synth.PRESETS["demo"], width=96, height=72,
                                                  supersample=1), 2)
    moved = [i for i, k in scene.change_types.items() if k == "moved"]
    assert len(moved) == 1
    obj = scene.object(moved[0])
    pb, pa = scene.object_center(obj, "before"), scene.object_center(obj, "after")
    assert np.linalg.norm(pb - pa) > 2 * obj.shape.footprint
    cam = scene.cameras("eval")[1]
    seen = {}
    for st in ("before", "after"):
        ids = scene.render(cam, st)["ids"]
        assert (ids == obj.id).sum() > 10
        seen[st] = np.argwhere(ids == obj.id).mean(0)
    assert np.linalg.norm(seen["before"] - seen["after"]) > 5  # pixels


def test_cameras(synth_tiny_scene):
    scene = synth_tiny_scene
    p = scene.preset
    before, after, ev = (scene.cameras(s) for s in ("before", "after", "eval"))
    assert (len(before), len(after), len(ev)) == (p.n_before, p.n_after, p.n_eval)
    assert before[0].image == "before/000.png" and before[0].set == "before"
    assert after[0].time == 1 and before[0].time == 0
    assert scene.cameras("eval_after")[1].image == "eval/after/001.png"
    cb = np.array([c.center for c in before])
    ca = np.array([c.center for c in after])
    ce = np.array([c.center for c in ev])
    assert np.linalg.norm(cb[:, None] - ca[None], axis=2).min() > 0.1  # different orbits
    assert scene.eval_min_distance_to_training() > 0.05
    R = p.room_half_size
    allc = np.concatenate([cb, ca, ce])
    assert (np.abs(allc[:, :2]) < R).all() and (allc[:, 2] > 0).all()
    for c in before + after + ev:  # every camera looks at the table centre (within jitter)
        ray = c.c2w[:3, 2]
        to_t = scene.target - c.center
        miss = np.linalg.norm(to_t - (to_t @ ray) * ray)
        assert miss < 0.1
    with pytest.raises(ValueError):
        scene.cameras("train")


def test_orbit_path(synth_tiny_scene):
    scene = synth_tiny_scene
    path = synth.orbit_path(scene, "after", 12)
    assert len(path) == 12 and all(c.set == "after" and c.time == 1 for c in path)
    cen = np.array([c.center for c in path])
    steps = np.linalg.norm(np.diff(cen, axis=0), axis=1)
    assert steps.min() > 0 and steps.max() < 1.5 * steps.min()  # smooth, evenly spaced
    train = scene.cameras("after")
    tol = 2 * np.sqrt(3) * scene.preset.jitter_m
    assert np.linalg.norm(cen[0] - train[0].center) < tol
    assert np.linalg.norm(cen[-1] - train[-1].center) < tol
    r = scene.render(path[5], "after", supersample=1)
    assert (r["ids"] > 0).sum() > 100


def test_overwrite_refused_and_allowed(tmp_path):
    out = tmp_path / "scene"
    out.mkdir()
    (out / "keep.txt").write_text("user data")
    with pytest.raises(GdiffError, match=str(out)):
        synth.make_scene(out, MICRO, seed=0)
    assert (out / "keep.txt").read_text() == "user data"
    synth.make_scene(out, MICRO, seed=0, overwrite=True)
    assert not (out / "keep.txt").exists() and (out / "meta.json").is_file()
    assert sorted(q.name for q in tmp_path.iterdir()) == ["scene"]  # no temp folders left
    empty = tmp_path / "empty"
    empty.mkdir()
    synth.make_scene(empty, MICRO, seed=0)  # an empty folder is fine
    assert (empty / "gt_cameras.json").is_file()


def test_options_and_presets():
    opts = from_config(synth.SynthOptions, {"preset": "tiny", "width": 80, "height": 60},
                       "synth")
    p = opts.to_preset()
    assert (p.width, p.height, p.n_before) == (80, 60, synth.PRESETS["tiny"].n_before)
    with pytest.raises(ConfigError):
        from_config(synth.SynthOptions, {"presett": "tiny"}, "synth")
    with pytest.raises(ConfigError, match="unknown"):
        synth.get_preset("huge")
    with pytest.raises(ConfigError):
        dataclasses.replace(synth.PRESETS["tiny"], lighting="disco")
    assert {"tiny", "demo", "lightchange"} <= set(synth.PRESETS)
    demo = synth.build_scene("demo", 0)
    assert sorted(demo.change_types.values()) == ["added", "moved", "removed"]


def test_cli(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(synth.PRESETS, "micro", dataclasses.replace(MICRO, name="micro"))
    out = tmp_path / "s"
    assert synth.main([str(out), "--preset", "micro", "--seed", "1"]) == 0
    assert json.loads((out / "meta.json").read_text())["seed"] == 1
    assert synth.main([str(out), "--preset", "micro"]) == 1
    assert "not empty" in capsys.readouterr().err
    assert synth.main([str(out), "--preset", "micro", "--overwrite"]) == 0
    more = tmp_path / "more"
    assert synth.main([str(more), "--preset", "micro", "--n-before", "3", "--n-after", "4",
                       "--n-eval", "1"]) == 0
    assert (len(list((more / "before").glob("*.png"))), len(list((more / "after").glob("*.png")))) \
        == (3, 4)
    assert json.loads((more / "meta.json").read_text())["preset_settings"]["n_after"] == 4
    assert synth.main([str(tmp_path / "bad"), "--preset", "micro", "--n-before", "1"]) == 1
    assert "n_before" in capsys.readouterr().err


def _inside(shape, p, tol=0.0):
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    if isinstance(shape, synth.Box):
        return (np.abs(x) <= shape.a + tol) & (np.abs(y) <= shape.b + tol) & \
            (z >= -tol) & (z <= shape.h + tol)
    if isinstance(shape, synth.Sphere):
        return np.linalg.norm(p - [0, 0, shape.r], axis=1) <= shape.r + tol
    rho = np.hypot(x, y)
    inz = (z >= -tol) & (z <= shape.h + tol)
    if isinstance(shape, synth.Cylinder):
        return inz & (rho <= shape.r + tol)
    return inz & (rho <= shape.r * (1 - z / shape.h) + tol)


@pytest.mark.parametrize("shape", [synth.Box(0.12, 0.08, 0.3), synth.Sphere(0.15),
                                   synth.Cylinder(0.1, 0.35), synth.Cone(0.14, 0.3)],
                         ids=lambda s: s.kind)
def test_shape_intersections(shape):
    """Rays from outside aimed at interior points hit the surface: just before the hit is
    outside, just after is inside, the normal is unit and faces the ray."""
    rng = np.random.default_rng(0)
    n = 4000
    c = np.array([0.0, 0.0, shape.hi[2] * (0.25 if shape.kind == "cone" else 0.5)])
    o = rng.normal(size=(n, 3))
    o = c + 1.5 * o / np.linalg.norm(o, axis=1, keepdims=True)
    target = c + rng.uniform(-0.2, 0.2, (n, 3)) * (shape.hi - shape.lo) * [1, 1, 0.5]
    assert _inside(shape, target).all()
    d = target - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, nrm = shape.intersect(o, d)
    assert np.isfinite(t).all()
    p = o + t[:, None] * d
    assert not _inside(shape, p - 1e-6 * d).any()
    assert _inside(shape, p + 1e-6 * d, tol=1e-9).all()
    assert np.allclose(np.linalg.norm(nrm, axis=1), 1.0, atol=1e-9)
    assert (np.einsum("ij,ij->i", nrm, d) < 0).all()
    # rays pointing away miss
    t2, _ = shape.intersect(o, -d)
    assert np.isinf(t2).all()


@pytest.mark.parametrize("kind", sorted(synth.TEXTURES))
def test_textures_detailed_and_deterministic(kind):
    """Every texture gives in-range albedo with fine detail (neighbouring 5 mm samples
    differ somewhere) and is a pure function of the point."""
    rng = np.random.default_rng(1)
    scene = synth.build_scene("demo", 0)  # 8 objects: every object texture is used
    params = [o.texture_params for o in scene.objects if o.texture == kind]
    params += [v for k, v in scene.room_textures.values() if k == kind]
    prm = params[0]
    p = rng.uniform(-0.5, 0.5, (3000, 3))
    if kind in ("wall_bricks", "tiles"):
        p[:, 2] = 0.0  # planar textures
    a = synth.texture_albedo(kind, p, prm)
    assert a.shape == (3000, 3) and a.min() >= 0.0 and a.max() <= 1.0
    assert np.array_equal(a, synth.texture_albedo(kind, p.copy(), prm))
    assert a.std(axis=0).max() > 0.05  # not flat
    b = synth.texture_albedo(kind, p + [0.005, 0.0, 0.0], prm)
    assert np.abs(a - b).max() > 0.05


def test_point_lamp_falloff_and_shadows():
    p = dataclasses.replace(synth.PRESETS["tiny"], lighting="lamp", width=80, height=60,
                            supersample=1, n_eval=2)
    scene = synth.build_scene(p, 0)
    L = scene.lighting["before"]
    assert L == scene.lighting["after"] and not L.suns and len(L.points) == 1
    lamp = L.points[0]
    # bare floor around the table: ambient + strength * cos / d^2
    pts = np.array([[2.0, 0.0, 0.0], [2.5, 1.2, 0.0], [-2.8, -2.0, 0.0], [1.2, -2.6, 0.0]])
    up = np.tile([0.0, 0.0, 1.0], (4, 1))
    e = scene.irradiance(pts, up, "before")
    v = np.asarray(lamp.position) - pts
    dist = np.linalg.norm(v, axis=1)
    expect = L.ambient * np.asarray(L.ambient_color) + np.outer(
        lamp.strength * v[:, 2] / dist ** 3, lamp.color)
    assert np.allclose(e, expect, rtol=1e-12)
    assert e[:, 0].argmax() == dist.argmin() and e[:, 0].argmin() == dist.argmax()
    # a point just beyond each object, as seen from the lamp, facing the lamp: ambient only
    for obj in scene.objects_in("before"):
        c = scene.object_center(obj, "before")
        away = (c - lamp.position) / np.linalg.norm(c - lamp.position)
        q = c + away * (np.linalg.norm(obj.shape.hi - obj.shape.lo) / 2 + 0.01)
        nq = -away[None]
        e_q = scene.irradiance(q[None], nq, "before")
        amb = L.ambient * (0.75 + 0.25 * nq[0, 2]) * np.asarray(L.ambient_color)
        assert np.allclose(e_q[0], amb, rtol=1e-12)
        assert (scene.irradiance(q[None], nq, "before", shadows=False)[0] > amb + 0.05).all()
    for cam in scene.cameras("eval"):
        r = scene.render(cam, "before")
        r0 = scene.render(cam, "before", shadows=False)
        assert r["shadow"].sum() > 5
        assert (_luma(r["rgb"])[r["shadow"]] < _luma(r0["rgb"])[r["shadow"]]).all()
