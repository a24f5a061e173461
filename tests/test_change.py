"""ID comparison: change types (added / removed / moved), evidence check, masks, stage files."""

import dataclasses
import json
import re
from collections import Counter

import cv2
import numpy as np
import pandas as pd
import pytest

from gdiff import synth
from gdiff.compare import (CompareOptions, change_masks, compare, compare_paths, decide,
                           detect_changes_pair, pose_stats)
from gdiff.compare import change as change_mod
from gdiff.compare import stage as cmp_stage
from gdiff.compare.change import replaced
from gdiff.errors import SceneError
from gdiff.parallel import fork_available
from gdiff.io import read_ids, read_image, read_mask, srgb_to_linear
from gdiff.segment import SegmentOptions, make_segmenter, segment_and_track, track_paths
from gdiff.segment import stage as seg_stage
from gdiff.track import TrackOptions, world_points

H, W = 40, 60


def _blank():
    return np.zeros((H, W), np.int64), np.full((H, W), 5.0, np.float32)


def test_types_from_drawn_id_maps():
    o = CompareOptions(min_area=4)
    stats = []
    for k in range(4):
        ids0, z0 = _blank()
        ids1, z1 = _blank()
        ids0[:], ids1[:] = 1, 1  # background, unchanged
        ids0[5:15, 5:15] = 2; z0[5:15, 5:15] = 4.0      # removed
        ids1[25:35, 5:15] = 3; z1[25:35, 5:15] = 4.0    # added
        ids0[5:15, 30:40] = 4; z0[5:15, 30:40] = 4.0    # moved, keeps its ID
        ids1[20:30, 40:50] = 4; z1[20:30, 40:50] = 4.0
        ids0[30:38, 50:58] = 5; ids1[30:38, 50:58] = 5  # unchanged object
        z0[30:38, 50:58] = z1[30:38, 50:58] = 4.5
        ids1[2:6, 40:56] = 6  # a segment only at t1, but the depth did not change (a shadow)
        stats.append((k, pose_stats(ids0, ids1, o, depth0=z0, depth1=z1)))
    df = decide(stats, o).set_index("id")
    assert df.loc[2, "type"] == "removed" and df.loc[3, "type"] == "added"
    assert df.loc[4, "type"] == "moved"
    assert not df.loc[[1, 5, 6], "changed"].any()
    m0, m1 = change_masks(ids0, ids1, df.index[df["changed"]])
    assert m0[5:15, 5:15].all() and m0[5:15, 30:40].all() and not m0[25:35, 5:15].any()
    assert m1[25:35, 5:15].all() and m1[20:30, 40:50].all() and not m1[2:6, 40:56].any()


def test_removed_and_added_lookalikes_pair_as_moved():
    o = CompareOptions(min_area=4)
    rgb0 = np.full((H, W, 3), 0.5, np.float32)
    rgb1 = rgb0.copy()
    rgb0[5:15, 5:15] = rgb1[25:35, 40:50] = (0.9, 0.2, 0.1)  # no depth: colour evidence
    ids0, z = _blank()
    ids1 = ids0.copy()
    ids0[5:15, 5:15] = 7
    ids1[25:35, 40:50] = 8
    st = pose_stats(ids0, ids1, o, rgb0, rgb1)
    df = decide([(0, st)], o).set_index("id")
    assert df.loc[7, "type"] == df.loc[8, "type"] == "moved"
    assert df.loc[7, "partner"] == 8


@pytest.fixture(scope="module")
def demo_paths():
    return _render_path("demo", 2, 6)


def test_change_types_and_masks_on_synthetic_scene(demo_paths):
    scene, frames, gt = demo_paths
    ids, _ = track_paths(frames, make_segmenter(SegmentOptions()), TrackOptions())
    masks, df = compare_paths(ids, frames, CompareOptions())
    # each GT changed object -> the type of the changed ID covering most of it
    found = {}
    for (p, t, i), m in ids.items():
        g = gt[(p, t, i)]["ids"]
        for oid in scene.changed_ids:
            sel = g == oid
            if sel.sum() < 40:
                continue
            v, c = np.unique(m[sel], return_counts=True)
            row = df[df["id"] == v[np.argmax(c)]]
            if len(row) and row["changed"].iloc[0]:
                found.setdefault(oid, set()).add(row["type"].iloc[0])
    for oid, typ in scene.change_types.items():
        assert typ in found.get(oid, set()), (oid, typ, found)
    # each changed object's largest changed ID is placed on it in the world (the frames'
    # cameras are the scene's own, so its frame): within a quarter of its box diagonal of the
    # box, at the time it is seen
    changed_ids = set(df.loc[df["changed"], "id"])
    for oid in scene.changed_ids:
        cover = Counter()
        for k, m in ids.items():
            v, c = np.unique(m[gt[k]["ids"] == oid], return_counts=True)
            cover.update(dict(zip(v.tolist(), c.tolist())))
        best = df.set_index("id").loc[max((t for t in cover if t in changed_ids), key=cover.get)]
        obj = scene.object(oid)
        state = "after" if best["n_t1"] > best["n_t0"] else "before"
        lo, hi = np.asarray(scene.object_bbox(obj, state), float)
        pos = best[["x", "y", "z"]].to_numpy(float)
        gap = np.linalg.norm(np.maximum(0, np.maximum(lo - pos, pos - hi)))
        assert np.isfinite(best["size"]) and gap <= 0.25 * np.linalg.norm(hi - lo), (oid, pos)
    f1 = []
    for (p, i), (m0, m1) in masks.items():
        g = gt[(p, "t0", i)]["changed"] | gt[(p, "t1", i)]["changed"]
        u = m0 | m1
        f1.append(2 * (u & g).sum() / max(u.sum() + g.sum(), 1))
        assert not (m0 & ~gt[(p, "t0", i)]["changed"]).sum() > 0.3 * max(m0.sum(), 1)
    assert np.mean(f1) > 0.8, f1


def test_pair_detection_with_depth(demo_paths):
    scene, frames, gt = demo_paths
    i = 3
    f0, f1 = frames[("p1", "t0", i)], frames[("p1", "t1", i)]
    m0, m1 = detect_changes_pair(f0["rgb"], f1["rgb"], f0["depth"], f1["depth"], f0["camera"].K)
    g = gt[("p1", "t0", i)]["changed"] | gt[("p1", "t1", i)]["changed"]
    u = m0 | m1
    assert 2 * (u & g).sum() / (u.sum() + g.sum()) > 0.7
    # without depth it still runs and returns masks of the image size
    n0, n1 = detect_changes_pair(f0["rgb"], f1["rgb"])
    assert n0.shape == n1.shape == g.shape and n0.dtype == bool


def _write_exr(path, rgb_srgb, depth):
    import OpenEXR

    lin = srgb_to_linear(rgb_srgb).astype(np.float16)
    ch = {"R": lin[..., 0].copy(), "G": lin[..., 1].copy(), "B": lin[..., 2].copy(),
          "A": np.ones(depth.shape, np.float16), "Z": depth.astype(np.float32)}
    path.parent.mkdir(parents=True, exist_ok=True)
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                 ch).write(str(path))


@pytest.mark.skipif(not fork_available(), reason="needs the fork start method")
def test_frames_segmented_and_poses_judged_in_parallel_give_the_serial_result(demo_paths):
    _, frames, _ = demo_paths
    seg = make_segmenter(SegmentOptions())
    ids, tracks = track_paths(frames, seg, TrackOptions())
    ids2, tracks2 = track_paths(frames, seg, TrackOptions(), workers=2)
    assert ids.keys() == ids2.keys() and all(np.array_equal(ids[k], ids2[k]) for k in ids)
    pd.testing.assert_frame_equal(tracks, tracks2)
    keys = {("p1", 0): 0, ("p1", 3): 0, ("p1", 1): 1, ("p1", 4): 1}
    out = [compare_paths(ids, frames, CompareOptions(), keys=keys, workers=w) for w in (1, 2)]
    (m1, df1), (m2, df2) = out
    assert m1.keys() == m2.keys()
    for k in m1:
        assert all(np.array_equal(a, b) for a, b in zip(m1[k], m2[k])), k
    pd.testing.assert_frame_equal(df1, df2)
    e1, e2 = df1.attrs["evidence3d"], df2.attrs["evidence3d"]
    assert e1.keys() == e2.keys() and "geometry" in e1
    for k in e1:
        assert e1[k][0] == e2[k][0] and all(np.array_equal(a, b)
                                            for a, b in zip(e1[k][1:], e2[k][1:]))


def test_stage_files(demo_paths, tmp_path, monkeypatch):
    scene, frames, _ = demo_paths
    n = 4
    cam0 = frames[("p1", "t0", 0)]["camera"]
    poses = {k: getattr(cam0, k) for k in ("width", "height", "fx", "fy", "cx", "cy")}
    poses["paths"] = {"p1": {"set": "before", "frames": [
        {"c2w": frames[("p1", "t0", i)]["camera"].c2w.tolist(), "key": i % 3 == 0,
         **({"image": f"before/{i:03d}.png"} if i % 3 == 0 else {})} for i in range(n)]}}
    res = tmp_path / "results" / "s"
    (res / "sequence").mkdir(parents=True)
    (res / "sequence" / "poses.json").write_text(json.dumps(poses))
    for t in ("t0", "t1"):
        for i in range(n):
            f = frames[("p1", t, i)]
            _write_exr(res / "render" / "p1" / t / f"{i:05d}.exr", f["rgb"], f["depth"])
    (res / "render" / "frames.json").write_text("{}")
    out = segment_and_track(res / "render", res / "sequence" / "poses.json", res / "instances",
                            SegmentOptions(), TrackOptions())
    assert out["frames"] == 2 * n
    ids = read_ids(res / "instances" / "p1" / "t1" / "00002.png")
    assert ids.shape == (cam0.height, cam0.width) and ids.max() > 0
    assert not (res / "instances" / "overlay").exists()  # debug overlays are opt-in
    tracks = pd.read_csv(res / "instances" / "tracks.csv")
    assert set(tracks.columns) >= {"id", "first", "last"}
    # the tracks that remain are numbered 1..K, and the ID maps hold no other IDs
    assert list(tracks["id"]) == list(range(1, len(tracks) + 1))
    used = set().union(*(np.unique(read_ids(f)).tolist()
                         for f in (res / "instances").rglob("*.png")))
    assert used - {0} == set(tracks["id"])
    summary = compare(res / "instances", res / "sequence" / "poses.json", res / "change",
                      CompareOptions())
    assert summary["changed"] >= 1
    kf = pd.read_csv(res / "change" / "keyframes.csv")
    assert list(kf.columns) == ["path", "frame", "image", "set", "time", "mask_t0", "mask_t1",
                                "mask_union", "judged", "light_changed"]
    assert not kf["light_changed"].any()  # the light did not change here
    assert list(kf["frame"]) == [0, 3] and (kf["time"] == 0).all()
    # where the stage could judge (coverage.csv, the judged maps): only against photos of both
    # times; this path has photos of one time, so every pixel was compared and none is listed
    cov = pd.read_csv(res / "change" / "coverage.csv")
    assert list(cov.columns) == cmp_stage.COVERAGE_COLUMNS and cov.empty
    assert kf["judged"].isna().all() and not (res / "change" / "p1" / "judged").exists()
    m = read_mask(res / kf["mask_union"].iloc[1])
    assert m.any() and (m == (read_mask(res / kf["mask_t0"].iloc[1])
                              | read_mask(res / kf["mask_t1"].iloc[1]))).all()
    ch = pd.read_csv(res / "change" / "changes.csv")
    assert set(ch["type"]) <= {"added", "removed", "moved"} and len(ch) == summary["changed"]
    cand = pd.read_csv(res / "change" / "candidates.csv")
    assert list(cand.columns) == ["instance", "place", "ids", "types", "n_t0", "n_t1",
                                  "n_confirmed", "area", "x", "y", "z", "size", "support",
                                  "colour", "photo", "photo_other", "photo_points", "own_px",
                                  "verdict"]
    assert {"x", "y", "z", "size"} <= set(ch.columns)
    kept = cand[cand["verdict"] != "dropped"]
    assert set(kept["instance"]) == set(ch["instance"])
    # a rendered frame gone (the workflow's temp() frames): a clear error, the outputs kept
    before = (res / "change" / "changes.csv").read_bytes()
    (res / "render" / "p1" / "t1" / "00002.exr").unlink()
    with pytest.raises(SceneError, match=r"00002\.exr: rendered frame not found \(1 of 8.*"
                                         r"re-run render"):
        compare(res / "instances", res / "sequence" / "poses.json", res / "change",
                CompareOptions())
    assert (res / "change" / "changes.csv").read_bytes() == before
    _write_exr(res / "render" / "p1" / "t1" / "00002.exr", frames[("p1", "t1", 2)]["rgb"],
               frames[("p1", "t1", 2)]["depth"])
    # overlays on request: one per frame, the same IDs; a later run without them removes them
    inst2 = res / "instances_overlays"
    segment_and_track(res / "render", res / "sequence" / "poses.json", inst2,
                      SegmentOptions(overlays=True), TrackOptions())
    over = sorted((inst2 / "overlay").rglob("*.jpg"))
    assert len(over) == 2 * n and read_image(over[0]).shape == (cam0.height, cam0.width, 3)
    assert np.array_equal(read_ids(inst2 / "p1" / "t1" / "00002.png"), ids)
    segment_and_track(res / "render", res / "sequence" / "poses.json", inst2, SegmentOptions(),
                      TrackOptions())
    assert not (inst2 / "overlay").exists()
    # compare judges the pixels the segmenter gave IDs: its alpha_min, from index.json
    segment_and_track(res / "render", res / "sequence" / "poses.json", inst2,
                      SegmentOptions(alpha_min=0.6), TrackOptions())
    assert json.loads((inst2 / "index.json").read_text())["alpha_min"] == 0.6
    used_alpha = []
    real_paths = cmp_stage.compare_paths

    def spy(*a, **k):
        used_alpha.append(k["alpha_min"])
        return real_paths(*a, **k)

    monkeypatch.setattr(cmp_stage, "compare_paths", spy)
    compare(inst2, res / "sequence" / "poses.json", res / "change2", CompareOptions())
    assert used_alpha == [0.6]
    # more tracks than a 16-bit ID map holds: a clear error before anything is written
    real = seg_stage.track_paths

    def too_many(*a, **k):
        ids, tr = real(*a, **k)
        return ids, pd.DataFrame({"id": np.arange(1, 70_001)})

    monkeypatch.setattr(seg_stage, "track_paths", too_many)
    with pytest.raises(SceneError, match="70000 instance tracks.*65535"):
        segment_and_track(res / "render", res / "sequence" / "poses.json", res / "inst3",
                          SegmentOptions(), TrackOptions())
    assert not (res / "inst3").exists()


# ------------------------------------------------------------------------------------------
# lighting changes and replaced objects
# ------------------------------------------------------------------------------------------

def _smooth_texture(rng, shape, sigma, n_channels=3):
    import cv2

    x = rng.normal(size=shape + (n_channels,)).astype(np.float32)
    x = cv2.GaussianBlur(x, (0, 0), sigma)
    return (x - x.min()) / (x.max() - x.min())


def _relight(rgb, gain, tone=True):
    """sRGB image under another light: linear colour x gain [H, W, 3], then a tone curve."""
    from gdiff.io import linear_to_srgb

    lin = srgb_to_linear(rgb) * gain
    if tone:
        lin = 1.0 - np.exp(-1.6 * lin)  # compresses contrast in bright areas
    return np.clip(linear_to_srgb(lin), 0, 1).astype(np.float32)


def test_texture_similarity_is_lighting_invariant():
    from gdiff.appearance import region_similarity, texture

    rng = np.random.default_rng(0)
    h, w = 60, 80
    base = 0.15 + 0.7 * _smooth_texture(rng, (h, w), 1.5)
    other = 0.15 + 0.7 * _smooth_texture(rng, (h, w), 1.5)
    jj, ii = np.mgrid[0:h, 0:w]
    # smooth light falloff, a warm-to-cold colour change and a hard shadow over a third
    gain = (0.6 + 0.8 * ii / w)[..., None] * np.array([0.7, 0.9, 1.4])
    gain = np.where((jj > 40)[..., None], gain * 0.25, gain)
    relit = _relight(base, gain)
    region = np.zeros((h, w), bool)
    region[5:55, 5:75] = True
    same = region_similarity(texture(base), texture(relit), region, 0.03)
    diff = region_similarity(texture(base), texture(_relight(other, gain)), region, 0.03)
    flat = np.full((h, w, 3), 0.5, np.float32)
    assert same > 0.6, same
    assert abs(diff) < 0.2, diff
    assert same > CompareOptions().same_similarity > diff
    assert np.isnan(region_similarity(texture(flat), texture(flat * 0.7), region, 0.03))


def _render_path(preset: str, seed: int, n: int):
    """A 128x96 synth scene and ground-truth renders of ``n`` before-orbit poses at both times:
    (scene, frames {("p1", t, i): rgb/depth/camera}, gt {key: render dict})."""
    p = dataclasses.replace(synth.get_preset(preset), width=128, height=96, supersample=1)
    scene = synth.build_scene(p, seed)
    frames, gt = {}, {}
    for i, cam in enumerate(synth.orbit_path(scene, "before", n)):
        for t, st in (("t0", "before"), ("t1", "after")):
            r = scene.render(cam, st)
            frames[("p1", t, i)] = dict(rgb=r["rgb"], depth=r["depth"], camera=cam)
            gt[("p1", t, i)] = r
    return scene, frames, gt


@pytest.fixture(scope="module")
def light_paths():
    return _render_path("lightchange", 1, 5)


def test_replaced_object_detected_under_lighting_change(light_paths):
    scene, frames, gt = light_paths
    old = [o for o in scene.objects if o.replaced_by]
    assert old, "lightchange preset has a replaced object"
    old_id, new_id = old[0].id, old[0].replaced_by
    ids, _ = track_paths(frames, make_segmenter(SegmentOptions()), TrackOptions())
    masks, df = compare_paths(ids, frames, CompareOptions())
    df = df.set_index("id")
    n_checked = 0
    for i in range(5):
        d0 = _dominant(ids[("p1", "t0", i)], gt[("p1", "t0", i)]["ids"], old_id)
        d1 = _dominant(ids[("p1", "t1", i)], gt[("p1", "t1", i)]["ids"], new_id)
        if d0 is None or d1 is None:
            continue
        n_checked += 1
        # the newcomer at the same spot does not inherit the old object's ID ...
        assert d0 != d1 and d0 > 0 and d1 > 0
        # ... and both are changes: the old one removed, the new one added (not "moved")
        assert df.loc[d0, "changed"] and df.loc[d0, "type"] == "removed"
        assert df.loc[d1, "changed"] and df.loc[d1, "type"] == "added"
    assert n_checked >= 3
    f1 = []
    for (p, i), (m0, m1) in masks.items():
        g = gt[(p, "t0", i)]["changed"] | gt[(p, "t1", i)]["changed"]
        u = m0 | m1
        f1.append(2 * (u & g).sum() / max(u.sum() + g.sum(), 1))
    assert np.mean(f1) > 0.85, f1


def _dominant(ids, gt_ids, oid, min_px=40):
    m = gt_ids == oid
    if m.sum() < min_px:
        return None
    v, c = np.unique(ids[m], return_counts=True)
    return int(v[np.argmax(c)])


def test_pair_without_depth_ignores_shadows_and_lighting():
    """Image pair without depth: a textured object is replaced by another, the light changes
    colour, strength and falloff, and a hard shadow falls across the background. Only the
    object is a change; pixel difference marks the shadow and the lighting too."""
    from gdiff.baselines import pixel_diff

    rng = np.random.default_rng(3)
    h, w = 96, 128
    bg = np.clip(np.array([0.55, 0.5, 0.4]) * (0.6 + 0.6 * _smooth_texture(rng, (h, w), 2.0)),
                 0, 1)
    jj, ii = np.mgrid[0:h, 0:w]
    disc = (ii - 80) ** 2 + (jj - 40) ** 2 < 16 ** 2
    obj0 = np.clip(np.array([0.2, 0.3, 0.8]) * (0.5 + 0.8 * _smooth_texture(rng, (h, w), 1.2)),
                   0, 1)
    obj1 = np.clip(np.array([0.25, 0.3, 0.75]) * (0.5 + 0.8 * _smooth_texture(rng, (h, w), 1.2)),
                   0, 1)
    rgb0 = np.where(disc[..., None], obj0, bg).astype(np.float32)
    after = np.where(disc[..., None], obj1, bg).astype(np.float32)
    gain = (0.5 + 1.0 * ii / w)[..., None] * np.array([0.8, 0.95, 1.3])
    shadow = (jj > 62) & (ii < 100)
    gain = np.where(shadow[..., None], gain * np.array([0.3, 0.35, 0.5]), gain)
    rgb1 = _relight(after, gain)
    m0, m1 = detect_changes_pair(rgb0, rgb1)
    u = m0 | m1
    f1 = 2 * (u & disc).sum() / max(u.sum() + disc.sum(), 1)
    base = pixel_diff(rgb0, rgb1).mask
    f1_base = 2 * (base & disc).sum() / max(base.sum() + disc.sum(), 1)
    assert f1 > 0.8, f1
    assert (u & shadow).sum() < 0.05 * shadow.sum()
    assert f1 > f1_base + 0.2, (f1, f1_base)


# ------------------------------------------------------------------------------------------
# renders of a fitted model: coverage by the training photos, render noise, fragments
# ------------------------------------------------------------------------------------------

def _plane_camera(x: float, f: float = 30.0):
    """A camera at (x, 0, 0) looking along +z (OpenCV axes) at the plane z = 5, W x H."""
    from gdiff.cameras import Camera

    c2w = np.eye(4)
    c2w[0, 3] = x
    return Camera(W, H, f, f, W / 2, H / 2, c2w)


def test_view_count_respects_frustum_and_occlusion():
    from gdiff.compare.coverage import DepthView, observed, view_count

    cam = _plane_camera(0.0)
    z = np.full((H, W), 5.0, np.float32)
    key = _plane_camera(4.0)  # sees world x in [-1, 9] on the plane
    zk = np.full((H, W), 5.0, np.float32)
    zk[:, 50:] = 3.0  # a nearer surface hides the plane from the key view there
    seen = observed(z, cam, [DepthView(key, zk)], depth_tol=0.05)
    u = np.arange(W) + 0.5
    x = (u - W / 2) / 30.0 * 5.0  # world x of each column on the plane
    uk = (x - 4.0) / 5.0 * 30.0 + W / 2  # its column in the key view
    expect = (uk >= 0) & (uk < 50)
    assert (seen == expect[None, :]).all()
    # two key views: the count adds up; min_views asks for both
    both = observed(z, cam, [DepthView(key, zk), DepthView(cam, z)], 0.05, min_views=2)
    assert (both == expect[None, :]).all()
    assert view_count(np.full((3, 3), np.nan), [DepthView(cam, z)], 0.05).sum() == 0
    # parallax: a plane point straight ahead of cam, seen by cam and key; their rays differ
    # by atan(4 / 5) = 38.7 degrees (a single direction would leave its depth undetermined)
    plane = np.full((H, W), 5.0, np.float32)
    views = [DepthView(cam, plane), DepthView(key, plane)]
    n, ang = view_count(np.array([[0.0, 0.0, 5.0]]), views, 0.05, parallax=True)
    assert n[0] == 2 and ang[0] == pytest.approx(np.degrees(np.arctan(4 / 5)), abs=1e-3)
    wide = observed(plane, cam, views, 0.05, min_views=2, min_parallax=30.0)
    narrow = observed(plane, cam, views, 0.05, min_views=2, min_parallax=45.0)
    assert wide[H // 2, W // 2 + 5] and not narrow.any()
    # seen: one view is enough (the photo shows the surface, its depth is not determined)
    det, shown = observed(plane, cam, views, 0.05, min_views=2, min_parallax=45.0, seen=True)
    assert not det.any() and (shown == observed(plane, cam, views, 0.05)).all()
    assert shown[H // 2, W // 2]


def test_view_window_sees_a_surface_through_depth_noise_but_not_behind_a_nearer_one():
    """A key view whose rendered depth is noisy from pixel to pixel (a fit to few photos):
    tested at one pixel it sees half of the plane it shows, at random; with a window of one
    pixel it sees all of it, and a surface nearer than the plane still hides it."""
    from gdiff.compare.coverage import DepthView, observed

    cam = _plane_camera(0.0)
    z = np.full((H, W), 5.0, np.float32)
    key = _plane_camera(4.0)
    zk = np.full((H, W), 5.0, np.float32)
    zk[(np.arange(H)[:, None] + np.arange(W)[None, :]) % 2 == 1] = 5.6  # +12 %, past tol
    zk[:, 20:] = 3.0  # a nearer surface hides the plane there
    u = np.arange(W) + 0.5
    uk = ((u - W / 2) / 30.0 * 5.0 - 4.0) / 5.0 * 30.0 + W / 2  # each column in the key view
    inside = (uk >= 0) & (uk < 20)
    one = observed(z, cam, [DepthView(key, zk)], depth_tol=0.05)
    win = observed(z, cam, [DepthView(key, zk, window=1)], depth_tol=0.05)
    assert 0.3 < one[:, inside].mean() < 0.7  # the noise decides, pixel by pixel
    assert win[:, inside].all()
    hidden = (uk >= 21) & (uk < W)  # behind the nearer surface, beyond the window's reach
    assert hidden.any() and not win[:, hidden].any() and not one[:, hidden].any()
    # the window's range is computed once per view and leaves invalid depths out
    v = DepthView(key, np.where(np.arange(W)[None, :] < 10, np.nan, zk).astype(np.float32), 1)
    lo, hi = v.depth_range()
    assert np.isinf(lo[:, :9]).all() and (lo[:, 11:19] == 5.0).all()
    assert (hi[:, 11:19] == 5.6).all() and v.depth_range()[0] is lo


def test_nearest_views_bound_the_work_but_not_the_result():
    """``max_views``: the views that share most of the frame decide first, the pixels they
    leave unobserved are tested against all views; the mask is the one of all views."""
    from gdiff.compare.coverage import DepthView, nearest_views, observed

    cam = _plane_camera(0.0)
    plane = np.full((H, W), 5.0, np.float32)
    rng = np.random.default_rng(3)
    views = []
    for x in (-9.0, -3.0, -1.5, 0.5, 1.0, 2.5, 4.0, 6.0, 30.0):  # 30: sees none of the frame
        zk = plane.copy()
        a = int(rng.integers(0, W - 12))
        zk[:, a:a + 12] = 3.0  # a nearer surface hides part of the plane from this view
        views.append(DepthView(_plane_camera(x), zk))
    P = world_points(plane, cam)
    # ranked on every point (stride 1) they are the three that see most of the frame
    near = [next(i for i, v in enumerate(views) if v is n)
            for n in nearest_views(P, views, 0.05, 3, stride=1)]
    share = [observed(plane, cam, [v], 0.05).mean() for v in views]
    assert len(near) == 3 and near == sorted(near)  # in their order
    assert min(share[i] for i in near) >= sorted(share, reverse=True)[2]  # the best three
    assert share[-1] == 0 and len(nearest_views(P, views, 0.05, 0)) == len(views) - 1
    for min_views, parallax in ((1, 0.0), (2, 10.0), (3, 20.0)):
        full = observed(plane, cam, views, 0.05, min_views, min_parallax=parallax)
        for k in (2, 3, 5):
            got = observed(plane, cam, views, 0.05, min_views, min_parallax=parallax,
                           max_views=k)
            assert (got == full).all(), (min_views, parallax, k)
    # (the best two views alone leave pixels unobserved that the others see)
    assert 0 < full.mean() < 1
    assert observed(plane, cam, nearest_views(P, views, 0.05, 2), 0.05, 3,
                    min_parallax=20.0).sum() < full.sum()


def test_observed_on_a_coarser_grid():
    """``step``: coverage tested on every step-th pixel of every step-th row; each block takes
    its tested pixel's answer, and pixels with no surface stay unobserved."""
    from gdiff.compare.coverage import DepthView, observed

    cam = _plane_camera(0.0)
    plane = np.full((H, W), 5.0, np.float32)
    plane[:, :7] = np.nan  # no surface on the left
    rng = np.random.default_rng(5)
    views = []
    for x in (-3.0, -1.0, 1.5, 4.0):
        zk = np.full((H, W), 5.0, np.float32)
        a = int(rng.integers(0, W - 12))
        zk[:, a:a + 12] = 3.0  # hides part of the plane from this view
        views.append(DepthView(_plane_camera(x), zk))
    for step in (2, 3):
        full = observed(plane, cam, views, 0.05, 2, min_parallax=10.0, seen=True)
        got = observed(plane, cam, views, 0.05, 2, min_parallax=10.0, seen=True, step=step)
        for f, g in zip(full, got):
            # every pixel with a surface answers as its block's tested (top-left) pixel
            block = f[::step, ::step].repeat(step, 0).repeat(step, 1)[:H, :W]
            assert (g == (block & np.isfinite(plane))).all(), step
            assert 0 < g.mean() < 1 and not g[:, :7].any()
            assert (g != f).mean() < 0.1  # a block-sized band along the borders


def test_spread_views_are_picked_for_parallax():
    """``spread``: among views that share most of the frame, the picked ones span the widest
    directions (the plain ranking takes the best-covering, here the closest together)."""
    from gdiff.compare.coverage import DepthView, nearest_views

    cam = _plane_camera(0.0)
    plane = np.full((H, W), 5.0, np.float32)
    xs = (-1.2, -0.4, -0.2, 0.0, 0.2, 0.4, 1.2, 8.0)  # 8.0 sees little of the frame
    views = [DepthView(_plane_camera(x), plane.copy()) for x in xs]
    P = world_points(plane, cam)

    def picked(**kw):
        return sorted(xs[next(i for i, v in enumerate(views) if v is n)]
                      for n in nearest_views(P, views, 0.05, 3, stride=1, **kw))

    assert picked() == [-0.2, 0.0, 0.2]
    assert picked(spread=True) == [-1.2, 0.0, 1.2]


def test_unobserved_region_is_not_a_change(caplog):
    """Path p1 is rendered at t1 where no after photo looked (its left part): the model renders
    something there (a surface nearer than before) that no photo supports. Only the object
    added where the after photo (the key view of p2) saw it is a change."""
    cam_a, cam_b = _plane_camera(0.0), _plane_camera(4.0)
    plane = np.full((H, W), 5.0, np.float32)
    ids = {k: np.ones((H, W), np.int64) for k in
           [("p1", "t0", 0), ("p1", "t1", 0), ("p2", "t0", 0), ("p2", "t1", 0)]}
    depth = {k: plane.copy() for k in ids}
    # the real added object: world x in [1.33, 2.67] at depth 4 (p1 columns 40-50, p2 10-20)
    ids[("p1", "t1", 0)][10:25, 40:50] = 3
    depth[("p1", "t1", 0)][10:25, 40:50] = 4.0
    ids[("p2", "t1", 0)][10:25, 10:20] = 3
    depth[("p2", "t1", 0)][10:25, 10:20] = 4.0
    # an unconstrained blob of the model at t1 where only before photos looked
    ids[("p1", "t1", 0)][10:25, 5:15] = 2
    depth[("p1", "t1", 0)][10:25, 5:15] = 4.0
    frames = {k: dict(depth=depth[k], camera=cam_a if k[0] == "p1" else cam_b) for k in ids}
    keys = {("p1", 0): 0, ("p2", 0): 1}
    # two poses: the 3D evidence that confirms a changed ID may come from one pose
    o = CompareOptions(min_area=4, observed_min_views=1, observed_min_parallax=0.0,
                       geometry_min_poses=1)
    _, blind = compare_paths(ids, frames, o)
    assert set(blind.loc[blind["changed"], "id"]) == {2, 3}  # without coverage: both
    with caplog.at_level("INFO", logger="gdiff.compare"):
        masks, df = compare_paths(ids, frames, o, keys=keys)
    # the log says how much was judged: each frame is its own key view at one time, and the
    # other time's photo (4 m aside) shows 36 of its 60 columns (60 %), less pixels of the
    # objects at t1 that photo does not see
    m = re.search(r"a photo of each time shows ([0-9.]+) %.* the other ([0-9.]+) % is not "
                  r"judged", caplog.text)
    assert m and 50 < float(m[1]) <= 60 and float(m[1]) + float(m[2]) == pytest.approx(100, abs=0.1)
    df = df.set_index("id")
    assert df.loc[3, "changed"] and df.loc[3, "type"] == "added"
    assert 2 not in df.index or not df.loc[2, "changed"]  # never judged: nothing saw it
    m0, m1 = masks[("p1", 0)]
    assert m1[10:25, 40:50].all() and not m1[10:25, 5:15].any() and not m0.any()
    # and the results say where: p1's judged map is "not judged" on the columns the after
    # photo (p2, 4 m aside) does not show, on the blob among them, and judged where both
    # photos look; the coverage table has the log's share
    from gdiff.compare.coverage import JUDGED_SEEN, NOT_JUDGED
    jd = df.attrs["judged"][("p1", 0)]
    assert jd.shape == (H, W) and jd.dtype == np.uint8
    assert (jd[:, :20] == NOT_JUDGED).all() and (jd[10:25, 5:15] == NOT_JUDGED).all()
    assert (jd[:, 36:] >= JUDGED_SEEN).mean() > 0.9
    cov = df.attrs["coverage"].set_index(["path", "frame"])
    assert list(cov["key"]) == [0, 1]
    row = cov.loc[("p1", 0)]
    assert row["surface"] == H * W and row["seen"] == (jd >= JUDGED_SEEN).sum()
    total = cov[["surface", "seen"]].sum()
    assert 100 * total["seen"] / total["surface"] == pytest.approx(float(m[1]), abs=0.05)


def test_semi_transparent_object_is_judged_above_alpha_min():
    """A fit to few photos draws an added object semi-transparent (rendered opacity 0.35 here).
    With the segmenter's ``alpha_min`` below that, its pixels show a surface, are judged and
    the object is a change; at 0.5 they show none and nothing is judged there."""
    cam_a, cam_b = _plane_camera(0.0), _plane_camera(4.0)
    ids = {k: np.ones((H, W), np.int64) for k in
           [("p1", "t0", 0), ("p1", "t1", 0), ("p2", "t0", 0), ("p2", "t1", 0)]}
    depth = {k: np.full((H, W), 5.0, np.float32) for k in ids}
    alpha = {k: np.ones((H, W), np.float32) for k in ids}
    for k, cols in ((("p1", "t1", 0), slice(40, 50)), (("p2", "t1", 0), slice(10, 20))):
        ids[k][10:25, cols] = 3
        depth[k][10:25, cols] = 4.0
        alpha[k][10:25, cols] = 0.35
    frames = {k: dict(depth=depth[k], alpha=alpha[k], camera=cam_a if k[0] == "p1" else cam_b)
              for k in ids}
    keys = {("p1", 0): 0, ("p2", 0): 1}
    o = CompareOptions(min_area=4, observed_min_views=1, observed_min_parallax=0.0,
                       geometry_min_poses=1)
    _, opaque = compare_paths(ids, frames, o, keys=keys, alpha_min=0.5)
    assert 3 not in set(opaque.loc[opaque["changed"], "id"])
    masks, df = compare_paths(ids, frames, o, keys=keys, alpha_min=0.25)
    assert set(df.loc[df["changed"], "id"]) == {3}
    assert masks[("p1", 0)][1][10:25, 40:50].all()


def test_thin_depth_noise_is_not_evidence():
    """A segment seen at one time only whose depth differs along thin streaks (a fitted
    model's depth noise along texture edges) is not confirmed; a solid change is."""
    o = CompareOptions(min_area=4)
    ids0, z0 = _blank()
    ids1, z1 = _blank()
    ids0[:], ids1[:] = 1, 1
    ids1[5:25, 5:25] = 2  # a piece of the background segmented apart at t1
    z1[5:25:3, 5:25] = 4.0  # every third row nearer: 35 % of its pixels, 1 px wide
    ids1[5:25, 35:55] = 3  # an object added at t1
    z1[5:25, 35:55] = 4.0
    st = pose_stats(ids0, ids1, o, depth0=z0, depth1=z1)
    assert st[2]["candidate"] and not st[2]["confirmed"], st[2]
    assert st[3]["confirmed"]
    raw = pose_stats(ids0, ids1, dataclasses.replace(o, evidence_open=0.0), depth0=z0,
                     depth1=z1)
    assert raw[2]["confirmed"]  # the streaks alone pass a per-pixel fraction test


def test_texture_only_change_needs_colour_and_a_missing_segment():
    """With depth unchanged, a texture that differs at the two times confirms a candidate only
    when its colours differ too and it is not a piece split off a segment that stays."""
    rng = np.random.default_rng(5)
    o = CompareOptions(min_area=4)
    base = np.clip(0.2 + 0.6 * _smooth_texture(rng, (H, W), 1.0), 0, 1).astype(np.float32)
    rgb0 = base.copy()
    rgb1 = base.copy()
    z = np.full((H, W), 5.0, np.float32)
    ids0 = np.ones((H, W), np.int64)
    ids1 = ids0.copy()
    # (a) a patch of the background re-rendered with other detail, same colours, split off
    #     the background segment at t1
    rgb1[4:20, 4:24] = np.clip(0.2 + 0.6 * _smooth_texture(rng, (16, 20), 1.0), 0, 1)
    ids1[4:20, 4:24] = 2
    # (b) an object replaced by one of the same shape, other texture and colours
    obj0 = np.clip(np.array([0.8, 0.3, 0.2]) * (0.4 + _smooth_texture(rng, (14, 18), 1.0)), 0, 1)
    obj1 = np.clip(np.array([0.2, 0.4, 0.8]) * (0.4 + _smooth_texture(rng, (14, 18), 1.0)), 0, 1)
    rgb0[22:36, 36:54], rgb1[22:36, 36:54] = obj0, obj1
    ids0[22:36, 36:54], ids1[22:36, 36:54] = 3, 4
    # (c) a patch re-rendered with other detail and other colours, split off the background
    #     segment at t1 - but the depth says the surface is where it was
    rgb1c, ids1c = rgb1.copy(), ids1.copy()
    rgb1c[24:38, 4:24] = np.clip(np.array([0.2, 0.4, 0.9])
                                 * (0.4 + _smooth_texture(rng, (14, 20), 1.0)), 0, 1)
    ids1c[24:38, 4:24] = 5
    st = pose_stats(ids0, ids1c, o, rgb0, rgb1c, z, z.copy())
    assert st[3]["confirmed"] and st[4]["confirmed"]
    assert st[2]["candidate"] and not st[2]["confirmed"]
    assert st[5]["candidate"] and not st[5]["confirmed"]
    # without depth there is no fragment rule: appearance alone decides (photo pairs)
    assert pose_stats(ids0, ids1c, o, rgb0, rgb1c)[5]["confirmed"]
    # without the colour requirement the re-rendered patch (a) passes on texture alone when it
    # is not a piece of a staying segment (here: no depth, so no fragment rule)
    loose = pose_stats(ids0, ids1, dataclasses.replace(o, texture_color_similarity=1.0),
                       rgb0, rgb1)
    strict = pose_stats(ids0, ids1, o, rgb0, rgb1)
    assert loose[2]["confirmed"] and not strict[2]["confirmed"]


def test_colour_of_an_added_object_cut_in_pieces_is_measured_against_the_staying_surface():
    """An added red box on a green and white cover, cut by the segmenter into strips (rows),
    seen where no depth is trusted (a sparse capture): the ring around a strip leaves out the
    other strips (they show at t1 only) and widens to the cover, so every strip measures the
    box against the cover, as the box in one piece does; the ring of its own width around an
    inner strip, all box, measures the box against itself. A strip farther from the cover
    than the widest ring keeps that ring, and so does every strip where depth is trusted."""
    from gdiff.compare.change import SURROUND_REACH, surround_colour_change

    rng = np.random.default_rng(3)
    o = CompareOptions(min_area=4)
    cover = np.where(_smooth_texture(rng, (H, W), 1.0)[..., :1] > 0.5, (0.2, 0.6, 0.25),
                     (0.85, 0.85, 0.8)).astype(np.float32)
    rgb0, rgb1 = cover.copy(), cover.copy()
    rgb1[12:] = np.clip(np.array((0.85, 0.1, 0.15))
                        * (0.8 + 0.4 * _smooth_texture(rng, (H - 12, W), 1.0)), 0, 1)
    ids0 = np.ones((H, W), np.int64)
    whole, cut = ids0.copy(), ids0.copy()
    whole[12:] = 2
    cut[12:20], cut[20:28], cut[28:36], cut[36:] = 3, 4, 5, 6
    # a sparse capture: a photo of each time shows every pixel, no depth is trusted
    shown, unknown = np.ones((H, W), bool), np.zeros((H, W), bool)
    sparse = dict(observed0=unknown, observed1=unknown, seen0=shown, seen1=shown)
    one = pose_stats(ids0, whole, o, rgb0, rgb1, **sparse)[2]["surround"]
    pieces = pose_stats(ids0, cut, o, rgb0, rgb1, **sparse)
    width = max(2, int(round(o.surround_width * max(H, W))))
    assert one >= o.confirm_colour
    for i in (3, 4, 5):
        assert pieces[i]["confirmed"] and pieces[i]["surround"] == pytest.approx(one, abs=0.1)
    for i in (4, 5):  # inner strips: their own ring is box only
        m = cut == i
        assert surround_colour_change(rgb0, rgb1, m, m, width, o.min_area) < 0.1
    assert 36 - 11 > SURROUND_REACH * width  # strip 6 lies beyond the widest ring
    m = cut == 6
    assert pieces[6]["surround"] == surround_colour_change(rgb0, rgb1, m, m, width, o.min_area)
    # where the depth is trusted the 3D evidence judges objects: the ring stays next to the
    # piece (the light right next to it is its light)
    dense = pose_stats(ids0, cut, o, rgb0, rgb1, observed0=shown, observed1=shown)
    m = cut == 4
    assert dense[4]["surround"] == surround_colour_change(rgb0, rgb1, m, m, width, o.min_area)


def test_surface_revealed_by_a_moved_object_is_not_added():
    """An object leaves; the table behind it, rendered at t1 with other colours and detail
    (the model saw it from few after photos), is segmented apart together with the object's
    contact rim. It is not an added instance: where it is not hidden at t0 behind the object
    the depth did not change; only the object is a change."""
    rng = np.random.default_rng(7)
    o = CompareOptions(min_area=4)
    rgb0 = np.clip(0.2 + 0.6 * _smooth_texture(rng, (H, W), 1.0), 0, 1).astype(np.float32)
    rgb1 = rgb0.copy()
    z0 = np.full((H, W), 5.0, np.float32)
    z1 = z0.copy()
    ids0 = np.ones((H, W), np.int64)
    ids1 = ids0.copy()
    ids0[10:30, 18:32] = 3  # the object with its rim (at table depth) at t0
    z0[10:30, 20:30] = 4.0
    rgb0[10:30, 18:32] = np.clip(np.array([0.9, 0.3, 0.2])
                                 * (0.4 + _smooth_texture(rng, (20, 14), 1.0)), 0, 1)
    ids1[10:30, 18:32] = 4  # the revealed table, rendered differently
    rgb1[10:30, 18:32] = np.clip(np.array([0.3, 0.5, 0.9])
                                 * (0.4 + _smooth_texture(rng, (20, 14), 1.0)), 0, 1)
    st = pose_stats(ids0, ids1, o, rgb0, rgb1, z0, z1)
    assert st[3]["confirmed"]  # the object left: its depth changed
    assert st[4]["candidate"] and not st[4]["confirmed"], st[4]
    # judged on appearance alone (no depth) the revealed region would pass
    assert pose_stats(ids0, ids1, o, rgb0, rgb1)[4]["confirmed"]


def test_pieces_of_one_object_form_one_instance():
    """A removed object segmented into two pieces (two IDs) is one instance; another removed
    object elsewhere is a second one; the smaller object put in that one's place (a
    replacement, seen at the other time) is a third."""
    o = CompareOptions(min_area=4)
    cam = _plane_camera(0.0)
    stats = []
    for k in range(3):
        ids0, z0 = _blank()
        ids1, z1 = _blank()
        ids0[:], ids1[:] = 1, 1
        ids0[10:30, 10:18], ids0[10:30, 18:26] = 2, 3  # one object, two pieces
        z0[10:30, 10:26] = 4.0
        ids0[10:30, 45:55] = 4  # another object
        z0[10:30, 45:55] = 4.0
        ids1[14:26, 47:53] = 5  # the replacement of 4, at t1
        z1[14:26, 47:53] = 3.0
        stats.append((k, pose_stats(ids0, ids1, o, depth0=z0, depth1=z1, focal=cam.fx,
                                    camera=cam)))
    df = decide(stats, o).set_index("id")
    assert df.loc[[2, 3, 4, 5], "changed"].all()
    assert df.loc[2, "instance"] == df.loc[3, "instance"] != df.loc[4, "instance"]
    assert df.loc[5, "instance"] not in (df.loc[2, "instance"], df.loc[4, "instance"])
    assert df.loc[1, "instance"] == 0


def test_moved_pairs_join_one_removed_and_one_added_object_but_do_not_chain():
    """A moved pair makes one instance of the removed object and the added one. Pieces of an
    added object that pair up as moved with two different removed objects (lookalike pieces
    of a textured surface cut differently at the two times) would chain all three into one
    instance: each object stays its own."""
    from gdiff.compare.change import _group_instances

    def row(i, t, x, partner=0, area=100.0):
        return dict(id=i, changed=True, type="moved" if partner else ("added" if t else
                                                                      "removed"),
                    partner=partner, n_t0=0 if t else 3, n_t1=3 if t else 0, area=area,
                    _pos=(np.array([x, 0.0, 0.0]), 0.1))

    df = pd.DataFrame([
        row(1, 0, 0.0, partner=2), row(2, 1, 1.0, partner=1),  # an object moved by 1 m
        row(3, 1, 5.0, partner=5, area=300.0), row(4, 1, 5.05, partner=6),  # two pieces
        row(5, 0, 7.0, partner=3), row(6, 0, 9.0, partner=4),  # ... paired with two objects
        row(7, 0, 9.02),  # a piece of the second of them
    ])
    _group_instances(df)
    inst = dict(zip(df["id"], df["instance"]))
    assert inst[1] == inst[2] == 1  # named by its largest member (the first on ties)
    assert inst[3] == inst[4] == 3
    assert inst[6] == inst[7] and len({inst[3], inst[5], inst[6]}) == 3
    place = dict(zip(df["id"], df["place"]))  # the pieces at one place, without moved pairs
    assert place[1] == 1 and place[2] == 2 and place[3] == place[4] == 3
    assert place[6] == place[7] == 6 and place[5] == 5


def test_each_place_of_a_moved_object_is_confirmed_on_its_own():
    """Two moved pairs. In the first, both places changed colour against their surroundings:
    the object moved, and both are kept as one moved object. In the second, only the removed
    place did; the added one is a piece of unchanged surface that paired up with it (its
    colour change is well under ``confirm_colour``). Pooled over the pair (weighted by its
    poses) the two would pass together; judged place by place, the added piece is dropped and
    the removed place is kept as a removed object of its own."""
    df = pd.DataFrame(dict(id=[1, 2, 3, 4], changed=[True] * 4, type=["moved"] * 4,
                           partner=[2, 1, 4, 3], instance=[1, 1, 3, 3], place=[1, 2, 3, 4],
                           colour=[0.6, 0.5, 0.6, 0.05], n_colour=[2, 2, 1, 1],
                           n_t0=[2, 0, 1, 0], n_t1=[0, 2, 0, 1], n_confirmed=[2, 2, 1, 1],
                           area=[300.0, 280.0, 500.0, 400.0], support=[0.0] * 4,
                           **{c: [0.0] * 4 for c in ("x", "y", "z", "size")}))
    cmp_stage._confirm_by_evidence(df, CompareOptions(), 8)
    cand = df.attrs["candidates"].set_index("place")
    assert list(cand["verdict"]) == ["kept: colour"] * 3 + ["dropped"]
    assert list(cand["instance"]) == [1, 1, 3, 3]
    row = df.set_index("id")
    assert list(row["changed"]) == [True, True, True, False]
    assert list(row["type"]) == ["moved", "moved", "removed", ""]
    assert list(row["partner"]) == [2, 1, 0, 0] and list(row["instance"]) == [1, 1, 3, 0]


def test_flat_object_removed_from_or_added_to_a_staying_surface_is_a_change():
    """A flat object (a pile of books) lies on a table at t0 and is gone at t1: its depth
    barely changes and at t1 its pixels belong to the table segment, which stays. Observed at
    both times, the table showing there at t1 and the object standing out from it at t0, its
    texture and colour change confirms it. A shadow that moved across the table (same
    chromaticity) and the contact rim of an object that moved away are not changes, and
    without key-view coverage the fragment rule still holds."""
    rng = np.random.default_rng(11)
    o = CompareOptions(min_area=4)
    wood = np.array([0.75, 0.5, 0.35], np.float32)
    table = np.clip(wood * (0.6 + 0.5 * _smooth_texture(rng, (H, W), 1.5)), 0, 1)
    rgb0, rgb1 = table.copy(), table.copy()
    z0 = np.full((H, W), 5.0, np.float32)
    ids0 = np.ones((H, W), np.int64)
    ids1 = ids0.copy()
    # (a) the books: lavender with white dots, 2 cm thick at 5 m (0.4 %: no depth change)
    books = np.tile(np.array([0.6, 0.55, 0.85], np.float32), (12, 16, 1))
    books[2::5, 2::5] = 1.0
    rgb0[4:16, 4:20], z0[4:16, 4:20], ids0[4:16, 4:20] = books, 4.98, 2
    # (b) a shadow cast on the table at t0 only: darker, same chromaticity
    rgb0[22:34, 4:20] = _relight(table[22:34, 4:20], np.full(3, 0.35, np.float32), tone=False)
    ids0[22:34, 4:20] = 3
    # (c) an object that moved away (depth changed) and its contact rim at table depth,
    #     coloured by the object's bounce light at t0
    z0[8:30, 38:50], ids0[8:30, 38:50] = 4.0, 4
    rgb0[8:30, 38:50] = np.array([0.2, 0.7, 0.3])
    rim = np.zeros((H, W), bool)
    rim[30:33, 36:52] = rim[22:30, 36:38] = rim[22:30, 50:52] = True  # hugs the object's base
    rgb0[rim], ids0[rim] = np.array([0.3, 0.6, 0.3]), 5
    z1 = np.full((H, W), 5.0, np.float32)
    seen = np.ones((H, W), bool)
    st = pose_stats(ids0, ids1, o, rgb0, rgb1, z0, z1, observed0=seen, observed1=seen)
    assert st[2]["candidate"] and st[2]["evidence"] < o.min_evidence  # flat: no depth change
    assert st[2]["confirmed"], st[2]
    assert st[3]["candidate"] and not st[3]["confirmed"], st[3]
    assert st[4]["confirmed"]  # the moved object itself: its depth changed
    assert st[5]["candidate"] and not st[5]["confirmed"], st[5]
    # without coverage a piece of a staying segment needs a change of geometry
    assert not pose_stats(ids0, ids1, o, rgb0, rgb1, z0, z1)[2]["confirmed"]
    df = decide([("pose", st)], o).set_index("id")
    assert df.at[2, "changed"] and df.at[2, "type"] == "removed"
    # the same books put onto the table instead (t0 and t1 swapped): added, and the shadow
    # and the rim, now at t1, are still not changes
    st = pose_stats(ids1, ids0, o, rgb1, rgb0, z1, z0, observed0=seen, observed1=seen)
    assert st[2]["confirmed"] and not st[3]["confirmed"] and not st[5]["confirmed"]
    df = decide([("pose", st)], o).set_index("id")
    assert df.at[2, "changed"] and df.at[2, "type"] == "added"


def test_object_one_photo_shows_is_judged_by_appearance_not_by_its_depth():
    """A sparse capture: one after photo shows cups put on a chair's seat. Seen from one
    direction only, their depth is undetermined, and the fit put them behind the seat, so the
    rendered depth says the seat at t0 hides them. Where the photos of both times show the
    surface but its depth is not determined, the cups are judged by their appearance and
    found; a patch of the seat cut differently at t1 (same texture) is not a change; where
    no photo showed the surface at one time nothing is judged."""
    rng = np.random.default_rng(5)
    o = CompareOptions(min_area=4)
    seat = np.clip(np.array([0.8, 0.78, 0.75], np.float32)
                   * (0.8 + 0.3 * _smooth_texture(rng, (H, W), 1.5)), 0, 1)
    rgb0, rgb1 = seat.copy(), seat.copy()
    ids0 = np.ones((H, W), np.int64)
    ids1 = ids0.copy()
    cups = np.clip(np.array([0.9, 0.8, 0.1], np.float32)
                   * (0.7 + 0.4 * _smooth_texture(rng, (10, 12), 1.0)), 0, 1)
    rgb1[10:20, 10:22], ids1[10:20, 10:22] = cups, 2
    ids1[26:36, 40:52] = 3  # the seat re-cut at t1
    z0 = np.full((H, W), 2.0, np.float32)
    z1 = z0.copy()
    z1[10:20, 10:22] = 3.0  # the cups' depth, wrong: behind the seat
    none, every = np.zeros((H, W), bool), np.ones((H, W), bool)
    st = pose_stats(ids0, ids1, o, rgb0, rgb1, z0, z1, observed0=none, observed1=none,
                    seen0=every, seen1=every)
    assert st[2]["candidate"] and st[2]["confirmed"], st[2]
    assert np.isnan(st[2]["evidence"])  # no depth evidence where the depth is not trusted
    assert not st[3]["confirmed"], st[3]
    df = decide([("pose", st)], o).set_index("id")
    assert df.at[2, "changed"] and df.at[2, "type"] == "added" and not df.at[3, "changed"]
    # with the depth trusted, the seat at t0 hides the cups: undecidable at this pose
    trusted = pose_stats(ids0, ids1, o, rgb0, rgb1, z0, z1, observed0=every, observed1=every)
    assert not trusted[2]["candidate"]
    # not shown by a photo of t0: nothing judged
    st = pose_stats(ids0, ids1, o, rgb0, rgb1, z0, z1, observed0=none, observed1=none,
                    seen0=none, seen1=every)
    assert not st[2]["observed"] and not st[2]["candidate"]


def test_few_trusted_pixels_do_not_make_an_object_the_same_surface_on_a_sparse_capture():
    """A sparse capture (depth trusted on a few pixels only): at t1 a red box stands at the
    image's left edge on a green and white cover, which the segmenter cuts differently at the
    two times around it, and the box's ID takes a strip of the cover too. Its depth is trusted
    on a few pixels of that strip, where it did not change. Those pixels do not make the box
    the same surface as the cover: it is judged by its appearance and its colours changed, so
    it is confirmed (and added). Pieces of the cover cut differently (same colours) are not.
    Where the trusted pixels are half of the region, its unchanged depth still decides (same
    surface, not confirmed). A region only seen is confirmed by its colours even where its
    texture persists (the fit draws a box it saw once faintly over what stood there), unless
    the depth is trusted there."""
    rng = np.random.default_rng(13)
    o = CompareOptions(min_area=4)
    cover = np.where(_smooth_texture(rng, (H, W), 1.0)[..., :1] > 0.5, (0.2, 0.6, 0.25),
                     (0.85, 0.85, 0.8)).astype(np.float32)
    rgb0, rgb1 = cover.copy(), cover.copy()
    rgb1[10:24, 0:12] = np.clip(np.array((0.55, 0.08, 0.1))
                                * (0.8 + 0.4 * _smooth_texture(rng, (14, 12), 1.0)), 0, 1)
    ids0 = np.ones((H, W), np.int64)
    ids1 = ids0.copy()
    ids0[0:30, 0:30], ids1[0:30, 0:30] = 5, 4  # the cover around the box, cut differently
    ids1[10:24, 0:16] = 2                      # the box and a strip of the cover next to it
    ids0[30:38, 36:50], ids1[30:38, 36:50] = 6, 3  # another piece of the cover
    z0 = np.full((H, W), 2.0, np.float32)
    z1 = z0.copy()
    shown = np.ones((H, W), bool)
    few = np.zeros((H, W), bool)
    few[10:24, 13:16] = few[30:38, 47:50] = True  # trusted: 3 of 16 columns, the cover
    assert 0 < few[ids1 == 2].mean() < 0.5 and few.mean() < 0.5

    def stats(rgb1, observed):
        return pose_stats(ids0, ids1, o, rgb0, rgb1, z0, z1, observed0=observed,
                          observed1=observed, seen0=shown, seen1=shown)

    st = stats(rgb1, few)
    assert st[2]["candidate"] and st[2]["evidence"] < o.min_evidence  # no depth change
    assert st[2]["confirmed"], st[2]
    for i in (3, 4, 5, 6):
        assert st[i]["candidate"] and not st[i]["confirmed"], (i, st[i])
    df = decide([("pose", st)], o).set_index("id")
    assert df.at[2, "changed"] and df.at[2, "type"] == "added"
    assert not df.loc[[3, 4, 5, 6], "changed"].any()
    # trusted on half of the region (still a sparse pose): its unchanged depth decides
    half = few.copy()
    half[10:24, 4:16] = True
    assert half[ids1 == 2].mean() >= 0.5 and half.mean() < 0.5
    assert st[2]["candidate"] and not stats(rgb1, half)[2]["confirmed"]
    # the box drawn as the cover's own texture, reddened: the texture persists, the colours
    # do not. Only seen: confirmed by its colours; its depth trusted everywhere: same surface
    faint = rgb0.copy()
    faint[10:24, 0:12] = cover[10:24, 0:12] * np.array((1.0, 0.25, 0.3), np.float32)
    st = stats(faint, few)
    assert st[2]["similarity"] >= o.same_similarity and st[2]["confirmed"], st[2]
    assert not stats(faint, shown)[2]["confirmed"]
    # with the training photos asked: only their "the two times differ" confirms by colour
    for answer in (True, False, None):
        st = pose_stats(ids0, ids1, o, rgb0, faint, z0, z1, observed0=few, observed1=few,
                        seen0=shown, seen1=shown, photos_differ=lambda region: answer)
        assert st[2]["confirmed"] is (answer is True), (answer, st[2])


def test_floor_resegmented_by_moved_glare_is_not_a_change():
    """A lighting change puts glare on a checker floor at t1: the washed-out part becomes a
    segment of its own and the floor's segments at t0 no longer match any at t1, so every
    piece is a candidate with a different texture and colour. The depth did not change
    anywhere, so none is confirmed; an object replaced in place by one of the same shape and
    depth (another ID of the same footprint at the other time) still is."""
    o = CompareOptions(min_area=4)
    jj, ii = np.mgrid[0:H, 0:W]
    checker = (((ii // 6) + (jj // 6)) % 2).astype(np.float32)
    floor = np.stack([0.15 + 0.5 * checker, 0.2 + 0.45 * checker, 0.3 + 0.4 * checker], -1)
    rgb0 = floor.copy()
    glare = 4.0 * np.exp(-(((ii - 28) / 18.0) ** 2 + ((jj - 18) / 16.0) ** 2))[..., None]
    rgb1 = np.clip(_relight(floor, np.array([1.2, 1.0, 0.7], np.float32))
                   + glare * np.array([1.0, 0.95, 0.8]), 0, 1).astype(np.float32)
    z = np.full((H, W), 5.0, np.float32)
    ids0 = np.where(ii < 30, 1, 2)
    ids1 = np.where(ii < 12, 4, np.where(ii < 42, 3, 5))  # the glare segment in between
    rng = np.random.default_rng(3)
    obj0 = np.clip(np.array([0.8, 0.3, 0.2]) * (0.4 + _smooth_texture(rng, (10, 8), 1.0)), 0, 1)
    obj1 = np.clip(np.array([0.2, 0.4, 0.8]) * (0.4 + _smooth_texture(rng, (10, 8), 1.0)), 0, 1)
    rgb0[2:12, 48:56], rgb1[2:12, 48:56] = obj0, obj1
    ids0[2:12, 48:56], ids1[2:12, 48:56] = 6, 7
    st = pose_stats(ids0, ids1, o, rgb0, rgb1, z, z.copy())
    for t in (1, 2, 3, 4, 5):
        assert st[t]["candidate"] and not st[t]["confirmed"], (t, st[t])
    assert st[3]["similarity"] != st[3]["similarity"]  # texture not used (NaN)
    assert st[6]["confirmed"] and st[7]["confirmed"]
    # judged on appearance alone (no depth), the glare segment would pass
    assert pose_stats(ids0, ids1, o, rgb0, rgb1)[3]["confirmed"]


def test_pose_stats_per_id_summaries_match_the_whole_image():
    """IDs are measured in their bounding boxes: areas, sizes, positions and histograms are
    those of the whole-image masks."""
    from gdiff.compare.change import _chroma_hist, _normalised_chroma
    from gdiff.track import world_points

    rng = np.random.default_rng(7)
    cam = _plane_camera(0.3)
    ids0 = cv2.resize(rng.integers(0, 9, (5, 6)), (W, H), interpolation=cv2.INTER_NEAREST)
    ids1 = ids0.copy()
    ids1[5:20, 10:30] = 9  # added at t1
    ids1[ids0 == 4] = 0  # removed at t1
    z0 = rng.uniform(4.0, 6.0, (H, W)).astype(np.float32)
    z1 = np.where(ids1 == 9, 3.0, z0).astype(np.float32)
    rgb0 = rng.uniform(0.1, 0.9, (H, W, 3)).astype(np.float32)
    rgb1 = rgb0.copy()
    o = CompareOptions(min_area=4)
    st = pose_stats(ids0, ids1, o, rgb0, rgb1, z0, z1, focal=cam.fx, camera=cam)
    assert set(st) == set(np.unique(np.r_[ids0.ravel(), ids1.ravel()])) - {0}
    assert st[9]["candidate"] and st[9]["area0"] == 0 and st[4]["area1"] == 0
    for t, r in st.items():
        time = 0 if r["area0"] else 1
        m = (ids0 if time == 0 else ids1) == t
        z = z0 if time == 0 else z1
        rgb = rgb0 if time == 0 else rgb1
        assert r["area0"] == (ids0 == t).sum() and r["area1"] == (ids1 == t).sum()
        assert r["size"] == pytest.approx(np.sqrt(m.sum()) * np.median(z[m]) / cam.fx)
        pts = world_points(z, cam)[m]
        assert np.allclose(r["pos"], np.median(pts, 0))
        assert np.array_equal(r["hist"], _chroma_hist(_normalised_chroma(rgb), m))


def test_decide_with_no_instance_gives_an_empty_table_with_its_columns():
    # a scene where segmentation found nothing to judge (e.g. no surface observed at both
    # times): no change, and the changed rows keep the columns that changes.csv needs
    df = decide([], CompareOptions())
    assert df.empty and df["changed"].dtype == bool
    changed = df[df["changed"]].drop(columns=["changed"])
    assert {"id", "type", "instance"} <= set(changed.columns)


def _box_scene_depth(camera, box: bool, floater: bool = False) -> np.ndarray:
    """z-depth [H, W] of a wall at world z = 5 seen by ``camera`` (looking along +z), with, when
    ``box``, the front face of a box (|x|, |y| <= 0.6, z = 4) standing in front of it and, when
    ``floater``, a patch of the wall (x in [1.2, 2.2], y in [-1, 0]) fitted at z = 4.3."""
    H, W = camera.height, camera.width
    u = (np.arange(W) + 0.5 - camera.cx) / camera.fx
    v = (np.arange(H) + 0.5 - camera.cy) / camera.fy
    cx = camera.c2w[0, 3]
    z = np.full((H, W), 5.0)
    for on, (x0, x1, y0, y1, zz) in ((floater, (1.2, 2.2, -1.0, 0.0, 4.3)),
                                     (box, (-0.6, 0.6, -0.6, 0.6, 4.0))):
        if on:
            x = cx + u[None, :] * zz + 0 * v[:, None]
            y = v[:, None] * zz + 0 * u[None, :]
            z[(x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)] = zz
    return z


def _wall_camera(x: float):
    """A 160 x 120 camera (f = 100 px) at world (x, 0, 0) looking along +z at the wall."""
    from gdiff.cameras import Camera

    c2w = np.eye(4)
    c2w[0, 3] = x
    return Camera(160, 120, 100.0, 100.0, 80.0, 60.0, c2w)


def _wall_rgb(camera, z: np.ndarray, box: np.ndarray | None = None) -> np.ndarray:
    """sRGB [H, W, 3]: a wall textured by its world x, y (so it renders the same at both
    times, wherever its depth was fitted), and a red ``box`` (bool [H, W])."""
    H, W = z.shape
    u = (np.arange(W) + 0.5 - camera.cx) / camera.fx
    v = (np.arange(H) + 0.5 - camera.cy) / camera.fy
    x = camera.c2w[0, 3] + u[None, :] * 5.0 + 0 * v[:, None]
    y = v[:, None] * 5.0 + 0 * u[None, :]
    g = 0.45 + 0.15 * np.sin(7 * x) * np.cos(5 * y)
    rgb = np.stack([g, g * 0.9, g * 0.8], -1).astype(np.float32)
    if box is not None:
        rgb[box] = (0.8, 0.1, 0.1)
    return rgb


def test_geometry_evidence_finds_an_object_merged_with_its_support():
    """The segmenter gave the added box and the wall behind it one ID at both times, so the ID
    comparison sees no change; the depth voted in 3D over the poses finds the box, and only
    it: a blob of wrong depth that shows at one pose only (fit noise) is voted away, and a patch
    the fit put nearer at t0 at every pose but that renders the same at both times (a floater)
    is not a change either. The shadow the box casts on the wall changes the wall's
    appearance but not its depth, like a flat object; hugging the box, it is not marked."""
    rng = np.random.default_rng(3)
    cams = [_wall_camera(x) for x in np.linspace(-1.0, 1.0, 9)]
    ids, frames, truth = {}, {}, {}
    for i, cam in enumerate(cams):
        z0, z1 = _box_scene_depth(cam, False, floater=True), _box_scene_depth(cam, True)
        truth[i] = z1 < 4.5
        rgb0, rgb1 = _wall_rgb(cam, z0), _wall_rgb(cam, z1, truth[i])
        x = cam.c2w[0, 3] + (np.arange(160) + 0.5 - 80.0) / 100.0 * 5.0
        y = (np.arange(120) + 0.5 - 60.0) / 100.0 * 5.0
        shadow = ((x[None, :] >= -0.4) & (x[None, :] <= 0.85) & (y[:, None] >= -0.4)
                  & (y[:, None] <= 0.85) & ~truth[i])
        rgb1[shadow] *= np.array([0.35, 0.4, 0.6], np.float32)  # bluish sky light
        if i == 4:  # a nearer, darker blob at t0 at this pose only, away from the box
            r, c = rng.integers(2, 8), rng.integers(2, 8)
            z0[r:r + 25, c:c + 25] *= 0.8
            rgb0[r:r + 25, c:c + 25] = (0.1, 0.3, 0.8)
        for t, z, rgb in (("t0", z0, rgb0), ("t1", z1, rgb1)):
            ids[("p1", t, i)] = np.ones(z.shape, np.int32)
            frames[("p1", t, i)] = dict(depth=z, camera=cam, rgb=rgb)
    masks, df = compare_paths(ids, frames, CompareOptions())
    assert not df["changed"].any()  # nothing for the ID comparison
    for i in range(len(cams)):
        m0, m1 = masks[("p1", i)]
        assert not m0.any(), i  # neither the one-pose blob nor the floater is a change
        hit = (m1 & truth[i]).sum() / truth[i].sum()
        assert hit > 0.75 and (m1 & ~truth[i]).sum() <= 0.05 * truth[i].sum(), (i, hit)
    off, _ = compare_paths(ids, frames, CompareOptions(geometry=False, flat=False))
    assert not any(m0.any() or m1.any() for m0, m1 in off.values())
    # without the appearance test the floater would count: it is there at every pose
    for f in frames.values():
        f.pop("rgb")
    no_rgb, _ = compare_paths(ids, frames, CompareOptions())
    assert sum(m0.sum() for m0, _ in no_rgb.values()) > 0


def test_id_change_without_3d_or_colour_change_is_not_a_change_under_unchanged_light():
    """The light is the same at both times and a box is added. At t1 the fit also rendered a
    piece of the far wall at a wrong depth, another one at each pose (fit noise), and the
    segmenter cut it apart: at every pose the ID comparison sees a new segment whose depth
    changed. It is no change: it is not where a surface appeared in 3D (the per-pose depths
    do not agree on a place) and its colour relative to the wall around it is the same. The
    box is kept: its shape changed in 3D."""
    cams = [_wall_camera(x) for x in np.linspace(-1.0, 1.0, 9)]
    ids, frames = {}, {}
    for i, cam in enumerate(cams):
        z0, z1 = _box_scene_depth(cam, False), _box_scene_depth(cam, True)
        box = z1 < 4.5
        P = world_points(z0, cam)  # the wall's world x, y at each pixel
        piece = (P[..., 0] >= -2.4) & (P[..., 0] <= -1.7) & (P[..., 1] >= 0.4) & (P[..., 1] <= 1.0)
        z1[piece] = 5.0 * (0.9 - 0.1 * (i % 4))  # 10 to 40 % nearer, another depth per pose
        rgb0, rgb1 = _wall_rgb(cam, z0), _wall_rgb(cam, z0, box)  # the wall as at t0
        ids0 = np.ones(z0.shape, np.int32)
        ids1 = np.ones(z0.shape, np.int32)
        ids1[box], ids1[piece] = 3, 2
        for t, z, rgb, m in (("t0", z0, rgb0, ids0), ("t1", z1, rgb1, ids1)):
            ids[("p1", t, i)] = m
            frames[("p1", t, i)] = dict(depth=z, camera=cam, rgb=rgb)
    _, df = compare_paths(ids, frames, CompareOptions())
    assert set(df.loc[df["changed"], "id"]) == {3}, df
    # both judged objects are listed with the figures of the verdict
    cand = df.attrs["candidates"].set_index("instance")
    assert sorted(cand.index) == [2, 3] and list(cand["ids"]) == ["2", "3"]
    assert cand.loc[3, "verdict"] == "kept: 3D" and cand.loc[3, "support"] >= 0.5
    assert cand.loc[2, "verdict"] == "dropped"
    assert cand.loc[2, "support"] < 0.5 and cand.loc[2, "colour"] < 0.25
    assert (cand["n_t0"] == 0).all() and (cand["n_confirmed"] == len(cams)).all()
    _, ungated = compare_paths(ids, frames, CompareOptions(confirm_support=0.0))
    assert set(ungated.loc[ungated["changed"], "id"]) == {2, 3}  # what the IDs alone say


def _wall_poster(camera):
    """The wall of :func:`_box_scene_depth` (no box) at ``camera``: z-depth [H, W], the world
    x and y [H, W] of each pixel on it, and bool [H, W] where a poster (|x + 0.2| <= 0.5,
    |y| <= 0.4) hangs on it."""
    z = _box_scene_depth(camera, False)
    u = (np.arange(camera.width) + 0.5 - camera.cx) / camera.fx
    v = (np.arange(camera.height) + 0.5 - camera.cy) / camera.fy
    x = camera.c2w[0, 3] + u[None, :] * 5.0 + 0 * v[:, None]
    y = v[:, None] * 5.0 + 0 * u[None, :]
    return z, x, y, (np.abs(x + 0.2) <= 0.5) & (np.abs(y) <= 0.4)


def test_flat_object_merged_with_its_support_is_found_in_3d(tmp_path):
    """A poster hangs on the wall at t0 and is gone at t1; the segmenter gave it and the wall
    one ID at both times and its depth is the wall's. Its change of appearance, voted in 3D
    over the poses, finds it at both times (the same surface), and only it. A poster that
    shows at one pose only (a fit artefact) is voted away. The changed voxels, written to
    disk and read back, show the poster from a camera that is not one of the poses."""
    from gdiff.compare.geometry import evidence_masks, read_evidence, write_evidence

    cams = [_wall_camera(x) for x in np.linspace(-1.0, 1.0, 9)]
    ids, frames, truth = {}, {}, {}
    for i, cam in enumerate(cams):
        z, x, y, truth[i] = _wall_poster(cam)
        rgb0, rgb1 = _wall_rgb(cam, z), _wall_rgb(cam, z)
        dots = (np.sin(40 * x) * np.sin(40 * y) > 0.5)[truth[i]]
        rgb0[truth[i]] = np.where(dots[:, None], (0.95, 0.95, 0.95), (0.55, 0.5, 0.85))
        if i == 4:  # another poster at t1 at this pose only
            rgb1[5:30, 120:150] = (0.2, 0.7, 0.3)
        for t, rgb in (("t0", rgb0), ("t1", rgb1)):
            ids[("p1", t, i)] = np.ones(z.shape, np.int32)
            frames[("p1", t, i)] = dict(depth=z.copy(), camera=cam, rgb=rgb)
    masks, df = compare_paths(ids, frames, CompareOptions())
    assert not df["changed"].any()  # nothing for the ID comparison
    for i in range(len(cams)):
        near = cv2.dilate(truth[i].astype(np.uint8), np.ones((13, 13), np.uint8)) > 0
        for m in masks[("p1", i)]:
            hit = (m & truth[i]).sum() / truth[i].sum()
            assert hit > 0.75 and not (m & ~near).any(), (i, hit)  # at most a blurred rim
    off, _ = compare_paths(ids, frames, CompareOptions(flat=False))
    assert not any(m0.any() or m1.any() for m0, m1 in off.values())
    alone, _ = compare_paths(ids, frames, CompareOptions(geometry=False))  # needs no geometry
    assert all(np.array_equal(alone[k][t], masks[k][t]) for k in masks for t in (0, 1))
    write_evidence(tmp_path / "evidence3d.npz", df.attrs["evidence3d"])
    ev = read_evidence(tmp_path / "evidence3d.npz")
    assert set(ev) == {"geometry", "flat"} and len(ev["flat"][1]) and not len(ev["geometry"][1])
    cam = _wall_camera(0.35)  # between the poses
    z = _box_scene_depth(cam, False)
    u = (np.arange(160) + 0.5 - 80.0) / 100.0
    v = (np.arange(120) + 0.5 - 60.0) / 100.0
    poster = (np.abs(0.35 + 5.0 * u[None, :] + 0.2) <= 0.5) & (np.abs(5.0 * v[:, None]) <= 0.4)
    near = cv2.dilate(poster.astype(np.uint8), np.ones((13, 13), np.uint8)) > 0
    for m in evidence_masks(ev, cam, z, z):
        assert (m & poster).sum() > 0.75 * poster.sum() and not (m & ~near).any()
    (tmp_path / "broken.npz").write_bytes(b"not a zip")
    with pytest.raises(SceneError, match="broken.npz.*compare"):
        read_evidence(tmp_path / "broken.npz")


def test_flat_change_the_photos_show_alike_is_the_fits_own():
    """The fit renders a poster on the wall at t0 at every pose, the same way (so the 3D vote
    keeps it), but the training photos of both times show the bare wall there: the fit's own
    error, left out. When the photos of t0 show the poster and those of t1 the bare wall, it
    is kept. Photos of one time only, or none, leave the evidence as it was."""
    cams = [_wall_camera(x) for x in np.linspace(-1.0, 1.0, 9)]
    keys = {("p1", i): i % 2 for i in range(len(cams))}  # even poses: t0 photos, odd: t1
    ids, frames, truth, bare, poster = {}, {}, {}, {}, {}
    for i, cam in enumerate(cams):
        z, _, _, truth[i] = _wall_poster(cam)
        rgb0, rgb1 = _wall_rgb(cam, z), _wall_rgb(cam, z)
        bare[i] = srgb_to_linear(rgb1)
        rgb0[truth[i]] = (0.55, 0.5, 0.85)
        poster[i] = srgb_to_linear(rgb0)
        for t, rgb in (("t0", rgb0), ("t1", rgb1)):
            ids[("p1", t, i)] = np.ones(z.shape, np.int32)
            frames[("p1", t, i)] = dict(depth=z.copy(), camera=cam, rgb=rgb)
    o = CompareOptions(observed_min_views=1, observed_min_parallax=0.0)

    def flat_pixels(photos, options=o):
        masks, _ = compare_paths(ids, frames, options, keys=keys, photos=photos)
        return sum(int((m0 & truth[i]).sum()) for (_, i), (m0, _) in masks.items())

    found = flat_pixels(None)
    assert found > 0.75 * sum(int(t.sum()) for t in truth.values())
    assert flat_pixels({k: bare[k[1]] for k in keys}) == 0  # photographed alike: the fit's own
    real = {k: (poster if t == 0 else bare)[k[1]] for k, t in keys.items()}
    assert flat_pixels(real) == found
    assert flat_pixels({k: bare[k[1]] for k in keys}, dataclasses.replace(
        o, flat_photo_contrast=0.0, photo_agree=0.0)) == found  # not asked
    # the flat evidence's photo test off, the photos of both visits still agree on the bare
    # wall at every key pose (compare.photo_agree): its own time's mask is cleared there
    agreed = flat_pixels({k: bare[k[1]] for k in keys},
                         dataclasses.replace(o, flat_photo_contrast=0.0))
    assert agreed < 0.5 * found
    one_time = {k: bare[k[1]] for k, t in keys.items() if t == 0}
    assert flat_pixels(one_time) == found  # the photos cannot tell


def test_only_seen_region_is_confirmed_by_its_colours_where_the_photos_differ_too():
    """A sparse capture of a wall: no surface's depth is trusted (each point is seen from too
    few directions), so every region is only seen. At t1 the fit renders a patch of the wall
    reddened, its texture still there (an object drawn faintly over the wall, or glass and
    metal rendered in other colours), and the segmenter cuts the wall differently around it
    at the two times. Its colours changed, so it is a change where the training photos of the
    two times differ there too (a red poster put up), and not where they look alike (the
    fit's own colours); without the photos its colours alone decide."""
    cams = [_wall_camera(x) for x in np.linspace(-1.0, 1.0, 9)]
    keys = {("p1", i): i % 2 for i in range(len(cams))}  # even poses: t0 photos, odd: t1
    ids, frames, truth, bare, poster = {}, {}, {}, {}, {}
    for i, cam in enumerate(cams):
        z, x, y, truth[i] = _wall_poster(cam)
        dots = (np.sin(25 * x) * np.sin(25 * y) > 0)[..., None]  # a patterned wallpaper
        rgb0 = (_wall_rgb(cam, z) * np.where(dots, 1.3, 0.7)).astype(np.float32)
        rgb1 = rgb0.copy()
        rgb1[truth[i]] *= np.array((1.0, 0.25, 0.3), np.float32)  # faint, texture kept
        bare[i], poster[i] = srgb_to_linear(rgb0), srgb_to_linear(rgb1)
        around = (np.abs(x + 0.2) <= 1.5) & (np.abs(y) <= 1.1)
        ids0, ids1 = np.ones(z.shape, np.int32), np.ones(z.shape, np.int32)
        ids0[around], ids1[around] = 3, 4  # the wall around it, cut differently
        ids1[truth[i]] = 2
        ids[("p1", "t0", i)], ids[("p1", "t1", i)] = ids0, ids1
        frames[("p1", "t0", i)] = dict(depth=z.copy(), camera=cam, rgb=rgb0)
        frames[("p1", "t1", i)] = dict(depth=z.copy(), camera=cam, rgb=rgb1)
    o = CompareOptions(observed_min_views=20, geometry=False, flat=False)

    def changed(photos):
        masks, df = compare_paths(ids, frames, o, keys=keys, photos=photos)
        marked = sum(int((m1 & truth[i]).sum()) for (_, i), (_, m1) in masks.items())
        return marked / sum(int(t.sum()) for t in truth.values()), df.set_index("id")

    real = {k: (bare if t == 0 else poster)[k[1]] for k, t in keys.items()}
    share, df = changed(real)
    assert share > 0.9 and df.at[2, "changed"] and df.at[2, "type"] == "added"
    assert not df.loc[[1, 3, 4], "changed"].any()
    share, df = changed({k: bare[k[1]] for k in keys})  # photographed alike: the fit's own
    assert share == 0 and not df.at[2, "changed"]
    share, df = changed(None)
    assert share > 0.9 and df.at[2, "changed"]


def test_photos_differ_against_their_spread_within_a_time():
    from gdiff.compare.photos import photos_differ

    rng = np.random.default_rng(0)
    grey = [np.array([0.3, 0.3, 0.3]) * (1 + 0.05 * rng.normal()) for _ in range(6)]
    grey2 = [np.array([0.3, 0.3, 0.3]) * (1 + 0.05 * rng.normal()) for _ in range(6)]
    assert photos_differ(grey, grey2, 3.0) is False
    assert photos_differ(grey, [g * 2.0 for g in grey2], 3.0) is True  # one stop brighter
    blue = [np.array([0.2, 0.2, 0.4]) * (1 + 0.05 * rng.normal()) for _ in range(6)]
    assert photos_differ(grey, blue, 3.0) is True  # same brightness, another colour
    assert photos_differ(grey[:1], blue, 3.0) is None  # one photo of t0: cannot tell
    # a spread as large as the difference (view-dependent shading) is no change
    shaded = [np.array([0.3, 0.3, 0.3]) * s for s in (0.5, 1.0, 2.0, 0.5, 1.0, 2.0)]
    assert photos_differ(shaded, [m * 1.3 for m in shaded], 3.0) is False


def test_view_means_count_only_the_surface_a_photo_shows():
    """Points on a wall at z = 5 count in a photo that renders the wall there, not in one whose
    rendered surface is nearer (an object in front of them at that time)."""
    from gdiff.compare.photos import KeyPhoto, view_means

    cam = _wall_camera(0.0)
    z = _box_scene_depth(cam, False)
    photo = np.zeros((cam.height, cam.width, 3), np.float32)
    photo[:, :80] = (0.2, 0.4, 0.6)
    photo[:, 80:] = (0.9, 0.9, 0.9)
    pts = np.array([[x, y, 5.0] for x in np.linspace(-1.5, -0.5, 5) for y in (-0.5, 0.0, 0.5)])
    covered = _box_scene_depth(cam, True)  # a box at z = 4 hides x in [-0.6, 0.6]
    m0, m1 = view_means(pts, [KeyPhoto(0, cam, z, photo), KeyPhoto(1, cam, covered, photo)],
                        tol=0.1)
    assert len(m0) == 1 and np.allclose(m0[0], (0.2, 0.4, 0.6))
    assert len(m1) == 1 and np.allclose(m1[0], (0.2, 0.4, 0.6))  # x < -0.6 still shows
    behind = pts[:, 0] >= -0.6
    assert behind.any()
    m0, m1 = view_means(pts[behind], [KeyPhoto(0, cam, z, photo),
                                      KeyPhoto(1, cam, covered, photo)], tol=0.1)
    assert len(m0) == 1 and m1 == []  # hidden behind the box at t1


def test_colour_is_not_believed_where_the_photos_of_both_visits_show_the_same_points_alike():
    """A red box is put in front of a textured wall between the visits. At the after visit's
    key poses the ID comparison keeps two objects by their rendered colours: the box, and a
    patch of wall the before model renders as a smeared guess from there (its colours differ
    from the after render's). Looked up in the before photos, the box's surface points show
    the wall behind it, unlike the after photo; the patch's points show the same wall as the
    after photo, no more differently than the rest of the wall: the patch is dropped, the box
    kept. A box that stood there at both visits is dropped too; with the test off, or under a
    change of light, the colours decide as before."""

    rng = np.random.default_rng(5)

    def shot(cam, box, time):
        z = _box_scene_depth(cam, box)
        rgb = _wall_rgb(cam, z)
        rgb[z < 5.0] = (0.8, 0.1, 0.1)
        noise = rng.normal(0, 0.01, rgb.shape).astype(np.float32)
        return z, srgb_to_linear(np.clip(rgb + noise, 0, 1))

    def judged(box_before, light_changed=False, **kw):
        o = CompareOptions(**kw)
        keys, frames, photos, ids = {}, {}, {}, {}
        for i, x in enumerate(np.linspace(-1.0, 1.0, 8)):
            t = i % 2  # even poses: before photos, odd: after photos
            cam = _wall_camera(float(x))
            z, photos[("p1", i)] = shot(cam, box_before or t == 1, t)
            keys[("p1", i)] = t
            frames[("p1", ("t0", "t1")[t], i)] = dict(depth=z, camera=cam)
            m = np.ones(z.shape, np.int32)
            if t == 1:
                m[z < 5.0] = 2  # the box
                m[10:40, 120:150] = 3  # the smeared patch of wall
            ids[("p1", ("t0", "t1")[t], i)] = m
            ids[("p1", ("t0", "t1")[1 - t], i)] = np.ones(z.shape, np.int32)
        key_photos = cmp_stage._key_photos(frames.get, keys, photos)
        df = pd.DataFrame(dict(id=[1, 2, 3], changed=[False, True, True],
                               type=["", "added", "added"], instance=[0, 2, 3],
                               place=[0, 2, 3], partner=[0, 0, 0],
                               colour=[np.nan, 0.6, 0.6], n_colour=[0, 1, 1],
                               n_t0=[8, 0, 0], n_t1=[8, 4, 4], n_confirmed=[0, 1, 1],
                               area=[1.0, 2000, 900], support=[np.nan, 0.0, 0.0],
                               **{c: [0.0] * 3 for c in ("x", "y", "z", "size")}))
        if o.confirm_colour_points > 0 and not light_changed:
            cmp_stage._photo_points(df, ids, key_photos, o)
        cmp_stage._confirm_by_evidence(df, o, 8, light_changed)
        return df.attrs["candidates"].set_index("instance")

    cand = judged(False)
    assert cand.at[2, "photo_points"] > 0.8 and cand.at[2, "verdict"] == "kept: colour"
    assert cand.at[3, "photo_points"] < 0.2 and cand.at[3, "verdict"] == "dropped"
    cand = judged(True)  # the box stood there at the before visit too
    assert cand.at[2, "photo_points"] < 0.2 and cand.at[2, "verdict"] == "dropped"
    for kw in (dict(confirm_colour_points=0.0), dict(light_changed=True)):
        cand = judged(False, **kw)
        assert (cand["verdict"] == "kept: colour").all(), kw


def test_colour_is_not_believed_for_an_object_only_the_other_visits_poses_show():
    """Four key poses, two per visit. A box added between the visits shows in the after
    render at the after visit's poses (its own time's: the after photos were taken there), and
    so does a box removed in the before render at the before visit's poses. A smear of the
    before model, seen from the after visit's poses only (none of the before photos was taken
    there), shows in the before render at those poses and nowhere at its own time's poses. All
    three changed colour against their surroundings; the smear is dropped, the boxes are kept.
    Pixels no photo of one of the times shows do not count for its own time's view. Its change
    in 3D still keeps it, and with the test off its colour does."""
    H, W = 40, 60
    keys = {("p1", 0): 0, ("p1", 1): 0, ("p1", 2): 1, ("p1", 3): 1}
    maps = {(p, t, i): np.ones((H, W), np.int32) for (p, i) in keys for t in ("t0", "t1")}
    for i in (2, 3):  # after poses
        maps[("p1", "t1", i)][10:20, 10:20] = 2  # the added box, its own time's render
        maps[("p1", "t0", i)][25:35, 30:50] = 4  # the before model's smear from there
    for i in (0, 1):  # before poses
        maps[("p1", "t0", i)][10:20, 40:55] = 3  # the removed box, its own time's render
    maps[("p1", "t0", 1)][0:4, 0:10] = 4  # the smear's ID at a before pose, ...
    shown = {k: np.ones((H, W), bool) for k in keys}
    shown[("p1", 1)][0:4, 0:10] = False  # ... where no after photo shows the surface

    def judged(support=0.0, **kw):
        o = CompareOptions(**kw)
        df = pd.DataFrame(dict(id=[1, 2, 3, 4], changed=[False, True, True, True],
                               type=["", "added", "removed", "removed"], instance=[0, 2, 3, 4],
                               place=[0, 2, 3, 4], partner=[0, 0, 0, 0],
                               colour=[np.nan, 0.6, 0.6, 0.6], n_colour=[0, 1, 1, 1],
                               n_t0=[4, 0, 2, 2], n_t1=[4, 2, 0, 0], n_confirmed=[0, 2, 2, 2],
                               area=[1.0, 100, 150, 200], support=[np.nan, 0.0, 0.0, support],
                               **{c: [0.0] * 4 for c in ("x", "y", "z", "size")}))
        cmp_stage._own_view(df, maps, keys, shown)
        cmp_stage._confirm_by_evidence(df, o, 8)
        return df.attrs["candidates"].set_index("instance")

    cand = judged()
    assert list(cand["own_px"]) == [200, 300, 0]
    assert list(cand["verdict"]) == ["kept: colour", "kept: colour", "dropped"]
    assert judged(support=0.9).at[4, "verdict"] == "kept: 3D"
    assert judged(confirm_colour_own_view=False).at[4, "verdict"] == "kept: colour"
    assert judged(min_area=250).at[2, "verdict"] == "dropped"  # 200 px: too few


def _counter_shot(x: float, size: tuple[int, int, float], grain: np.ndarray, cells: float,
                  half: float, colour) -> tuple:
    """A pinhole camera (``size`` = width, height, focal in pixels) at (x, 0, 0) looking down +z
    at a counter, the plane z = 5 textured with ``grain`` (grey values, ``cells`` cells per
    scene unit, the counter's point (-10, -10) at its corner), with a box's front face 10 cm in
    front of it, a square of half side ``half`` centred on the z axis in ``colour`` (none for
    ``half`` 0). Returns (camera, z-depth float [H, W], linear RGB float [H, W, 3])."""
    from gdiff.cameras import Camera

    W, H, f = size
    c2w = np.eye(4)
    c2w[0, 3] = x
    cam = Camera(W, H, f, f, W / 2, H / 2, c2w)
    u = (np.arange(W) + 0.5 - cam.cx) / f
    v = (np.arange(H) + 0.5 - cam.cy) / f
    z = np.full((H, W), 5.0)
    wx, wy = x + u[None, :] * z, v[:, None] * z
    g = grain[((wy + 10) * cells).astype(int), ((wx + 10) * cells).astype(int)]
    rgb = np.repeat(g[..., None], 3, -1)
    if half > 0:
        box = (np.abs(wx) < half) & (np.abs(wy) < half)
        z = np.where(box, 4.9, z)
        rgb[box] = colour
    return cam, z, rgb


def test_point_lookup_sees_past_a_fine_texture_a_pixel_off():
    """A dull red can stands on a granite counter (speckle one pixel fine) at the after visit.
    The fit put the after visit's depth a little too near, so the can's points and the
    counter's land a pixel or two off their place in the before photo. Compared pixel to
    pixel, the counter's speckle differs there as much as the can does, and the can is not
    told from it; compared in the photos blurred by a few pixels, the speckle averages to the
    counter's grey and the can stands out, while a patch of counter taken for a change stays
    as unremarkable as the rest."""
    from gdiff.compare.photos import KeyPhoto, point_photo_counts

    rng = np.random.default_rng(11)
    grain = rng.uniform(0.1, 0.9, (2000, 2000)).astype(np.float32)  # 1 cm cells of granite

    def shot(x, can):  # the can's front face, 10 cm in front of the counter
        return _counter_shot(x, (640, 480, 500.0), grain, 100, 0.4 if can else 0.0,
                             (0.5, 0.32, 0.3))

    cam, z, rgb = shot(0.0, True)
    own = KeyPhoto(1, cam, z * 0.95, rgb)  # the fit put it all 5 % too near
    others = [KeyPhoto(0, c, zz, im) for c, zz, im in (shot(x, False) for x in (-0.3, 0.3))]
    H, W = z.shape
    ids = np.ones((H, W), np.int32)
    ids[z < 5.0] = 2  # the can
    ids[50:150, 50:150] = 3  # a patch of counter the segmenter cut differently
    changed = np.array([False, False, True, True])
    shares = {}
    for blur in (0.0, 1 / 320):
        total, above = point_photo_counts(own, ids, changed, others, 0.02, 4, blur=blur)
        shares[blur] = above / np.maximum(total, 1)
        assert total[2] > 10000 and total[3] > 5000
    assert shares[0.0][2] < 0.5  # pixel to pixel, the can is lost in the speckle
    assert shares[1 / 320][2] > 0.9  # blurred, it stands out
    assert shares[0.0][3] < 0.2 and shares[1 / 320][3] < 0.2


def test_point_lookup_sees_past_the_other_visits_exposure():
    """A white box stands on a grey counter at the after visit; the before visit's camera
    exposed one stop brighter, so the counter there looks as bright as the box does in the
    after photo. Compared as they are, the box's points look like the counter in the before
    photos and every unchanged point differs by the stop; with the two photos' exposure (the
    unchanged surface's median difference) taken out, the box stands out and a patch of
    counter taken for a change does not."""
    from gdiff.compare.photos import KeyPhoto, point_photo_counts

    rng = np.random.default_rng(5)
    grain = rng.uniform(0.25, 0.35, (400, 400)).astype(np.float32)  # 5 cm cells of counter

    def shot(x, box, exposure):
        cam, z, rgb = _counter_shot(x, (320, 240, 250.0), grain, 20, 0.6 if box else 0.0, 0.6)
        return cam, z, rgb * exposure

    cam, z, rgb = shot(0.0, True, 1.0)
    own = KeyPhoto(1, cam, z, rgb)
    others = [KeyPhoto(0, c, zz, im) for c, zz, im in (shot(x, False, 2.0) for x in (-0.3, 0.3))]
    H, W = z.shape
    ids = np.ones((H, W), np.int32)
    ids[z < 5.0] = 2  # the box
    ids[20:70, 20:70] = 3  # a patch of counter the segmenter cut differently
    total, above = point_photo_counts(own, ids, np.array([False, False, True, True]), others,
                                      0.02, 4)
    share = above / np.maximum(total, 1)
    assert total[2] > 2000 and total[3] > 1000
    assert share[2] > 0.9
    assert share[3] < 0.2


@pytest.mark.parametrize("fit_took_it_up", [False, True])
def test_visit_exposure_brings_both_visits_photos_to_one_exposure(fit_took_it_up):
    """The after visit's camera exposed one stop brighter, and a white box was put on the grey
    counter. Photos of the two visits compared as they are differ on the counter by the stop
    (the region photo test calls it a change); brought to one exposure by the renders at their
    cameras they agree on the counter and still differ on the box. Whether the fit learnt the
    stop as a change over time (each time's render has its visit's exposure) or its per-image
    correction took it up (both renders at the model's own exposure), both photos come out at
    one exposure."""
    from gdiff.compare.photos import photos_differ, visit_exposure

    rng = np.random.default_rng(3)
    grain = rng.uniform(0.25, 0.35, (400, 400)).astype(np.float32)
    gain = {0: 1.0, 1: 2.0}  # each visit's exposure
    scenes = {t: [_counter_shot(x, (160, 120, 125.0), grain, 20, 0.6 if t else 0.0, 0.6)[2]
                  for x in (-0.2, 0.2)] for t in (0, 1)}
    photos = {t: [s * gain[t] for s in scenes[t]] for t in (0, 1)}
    fixed = {}
    for t in (0, 1):
        fixed[t] = []
        for k, photo in enumerate(photos[t]):
            own, other = scenes[t][k], scenes[1 - t][k]  # the same camera at both times
            if not fit_took_it_up:
                own, other = own * gain[t], other * gain[1 - t]
            fixed[t].append(visit_exposure(photo, [own, other]))
    counter = np.zeros((120, 160), bool)
    counter[:, :25] = True  # left of the box at both cameras
    box = np.zeros((120, 160), bool)
    box[50:70, 70:90] = True
    for region, changed in ((counter, False), (box, True)):
        raw = [[p[region].mean(0) for p in photos[t]] for t in (0, 1)]
        one = [[p[region].mean(0) for p in fixed[t]] for t in (0, 1)]
        assert photos_differ(*raw, 3.0) is True
        assert photos_differ(*one, 3.0) is changed
    ratio = fixed[1][0][counter].mean() / fixed[0][0][counter].mean()
    assert abs(ratio - 1) < 0.02
    expected = 1.0 if fit_took_it_up else np.sqrt(2.0)  # the model's exposure, or the mean
    assert fixed[0][0][counter].mean() / scenes[0][0][counter].mean() == pytest.approx(
        expected, rel=0.02)


def test_point_lookup_reference_is_local_and_outlines_are_left_out():
    """The reference of the per-point photo test is taken around each pixel: where the
    lookup is poorer (half of the view, larger differences on unchanged surface) the cut is
    higher there only. And an ID's outline does not count."""
    from gdiff.compare.photos import _local_cut, interior

    rng = np.random.default_rng(2)
    H, W = 60, 80
    pix = np.arange(H * W)
    cols = pix % W
    values = np.where(cols < 40, 0.1, 1.0) + rng.normal(0, 0.02, H * W)
    cut = _local_cut(pix, values, (H, W), 0.125, 0.9, fallback=-1.0).reshape(H, W)
    inner = cut[6:-6]  # away from the corners (fewer than 50 values around them)
    assert 0.1 < inner[:, :30].max() < 0.2 and 1.0 < inner[:, 50:].min() < 1.1
    assert (_local_cut(pix[:10], values[:10], (H, W), 0.125, 0.9, fallback=-1.0) == -1).all()
    ids = np.zeros((H, W), np.int32)
    ids[10:30, 10:40] = 7
    inner = interior(ids, 2)
    assert inner[14:26, 14:36].all() and not inner[10, 10:40].any()
    assert interior(ids, 0).all()


def test_moving_light_with_no_object_change_gives_no_change():
    """The lightchange preset with every object left in place: the sun moves and changes
    colour, hard shadows and highlights move. Each frame's depth also gets its own smooth
    error (a fitted model's depth is not exact, and differs between the two times). With
    errors below ``depth_change_rel`` nothing is a change; with blobs of up to 10 % of the
    depth, which the ID comparison takes for changes at single poses, the 3D geometry vote
    still adds nothing (the errors do not agree between poses). The moved shadows change the
    appearance of so much of the scene that the flat-object evidence is not used (it would
    mark them without its ``flat_max_rate``)."""
    p = dataclasses.replace(synth.get_preset("lightchange"), width=128, height=96,
                            supersample=1, n_moved=0, n_replaced=0)
    scene = synth.build_scene(p, 2)
    renders = [(cam, scene.render(cam, "before"), scene.render(cam, "after"))
               for cam in synth.orbit_path(scene, "before", 8)]
    assert not any(np.array_equal(r0["rgb"], r1["rgb"]) for _, r0, r1 in renders)

    def frames_with(error: float) -> dict:
        rng = np.random.default_rng(0)
        frames = {}
        for i, (cam, r0, r1) in enumerate(renders):
            for t, r in (("t0", r0), ("t1", r1)):
                noise = cv2.GaussianBlur(rng.normal(0, 1, r["depth"].shape).astype(np.float32),
                                         (0, 0), 6)
                noise *= error / max(float(np.abs(noise).max()), 1e-6)
                frames[("p1", t, i)] = dict(rgb=r["rgb"], depth=r["depth"] * (1 + noise),
                                            camera=cam)
        return frames

    frames = frames_with(0.03)
    ids, _ = track_paths(frames, make_segmenter(SegmentOptions()), TrackOptions())
    masks, df = compare_paths(ids, frames, CompareOptions())
    assert not df["changed"].any()
    assert not any(m0.any() or m1.any() for m0, m1 in masks.values())
    ungated, _ = compare_paths(ids, frames, CompareOptions(flat_max_rate=1.0))
    assert sum(m0.sum() + m1.sum() for m0, m1 in ungated.values()) > 0
    frames = frames_with(0.10)
    ids, _ = track_paths(frames, make_segmenter(SegmentOptions()), TrackOptions())
    on, _ = compare_paths(ids, frames, CompareOptions())
    off, _ = compare_paths(ids, frames, CompareOptions(geometry=False))
    # the geometry adds no pixel; under the change of light it confirms ID changes, and the
    # depth errors change no shape, so some ID changes are dropped
    assert not any((on[k][t] & ~off[k][t]).any() for k in on for t in (0, 1))


def test_object_relit_and_tracked_apart_is_not_a_change_but_a_swap_is():
    """A change of light: a bluish light comes in through blinds, whose hard shadow bars
    cross box A and the wall around it. The tracker could not match box A's two looks (ID 2 at
    t0, ID 3 at t1): the bars change its texture and colour in the images, so the ID comparison
    takes it for a removed and an added box. Box B was swapped for a box of the same shape and
    size but another pattern and colour (ID 4, then ID 5). Neither changes any depth. Relative
    to the wall next to each box, which the same light falls on, box A's colour stays and box
    B's does not: only box B is a change."""
    cams = [_wall_camera(x) for x in np.linspace(-1.0, 1.0, 9)]
    ids, frames = {}, {}
    for i, cam in enumerate(cams):
        H, W = cam.height, cam.width
        z = np.full((H, W), 5.0)
        front = world_points(np.full((H, W), 4.0), cam)  # the boxes' front plane, z = 4
        boxes = {}
        for name, (x0, x1) in (("A", (-1.4, -0.4)), ("B", (0.4, 1.4))):
            boxes[name] = ((front[..., 0] >= x0) & (front[..., 0] <= x1)
                           & (np.abs(front[..., 1]) <= 0.5))
            z[boxes[name]] = 4.0
        P = world_points(z, cam)  # world x, y of each pixel's surface
        x, y = P[..., 0], P[..., 1]
        wall = np.stack([0.55 + 0.02 * np.sin(3 * x), 0.5 + 0 * x, 0.45 + 0 * x], -1)
        stripes = (0.5 + 0.4 * np.sin(25 * x))[..., None]
        ribs = 0.35 * np.cos(25 * x)[..., None]  # box A is ribbed: lit from the left, then right
        rgb0, rgb1 = wall.copy(), wall.copy()
        rgb0[boxes["A"]] = ((0.6 + ribs) * np.array([0.2, 0.5, 0.8]))[boxes["A"]]
        rgb1[boxes["A"]] = ((0.6 - ribs) * np.array([0.2, 0.5, 0.8]))[boxes["A"]]
        rgb0[boxes["B"]] = (stripes * np.array([0.85, 0.2, 0.15]))[boxes["B"]]
        dots = ((np.sin(30 * x) * np.sin(30 * y) > 0.3)[..., None]
                * np.array([0.1, 0.6, 0.2]) + 0.15)
        rgb1[boxes["B"]] = dots[boxes["B"]]  # the other box
        rgb1 *= np.array([0.85, 0.9, 1.0])  # cooler light everywhere
        bars = (np.sin(4 * (x + y)) > 0.0) & (x < 0.0)  # the blinds' shadow, left half
        rgb1[bars] *= np.array([0.2, 0.3, 0.6])
        for t, rgb, a, b in (("t0", rgb0, 2, 4), ("t1", rgb1, 3, 5)):
            m = np.ones((H, W), np.int32)
            m[boxes["A"]], m[boxes["B"]] = a, b
            ids[("p1", t, i)] = m
            frames[("p1", t, i)] = dict(depth=z.copy(), camera=cam,
                                        rgb=np.clip(rgb, 0, 1).astype(np.float32))
    _, df = compare_paths(ids, frames, CompareOptions())
    changed = set(df.loc[df["changed"], "id"])
    assert changed == {4, 5}, df
    _, ungated = compare_paths(ids, frames, CompareOptions(confirm_support=0.0))
    assert {2, 3} <= set(ungated.loc[ungated["changed"], "id"])  # what the ID comparison saw


def test_chroma_hist_bins_as_histogram2d():
    """The chromaticity histogram counts into the bins np.histogram2d gives over [0, 1),
    values on bin edges included."""
    from gdiff.compare.change import _chroma_hist
    rng = np.random.default_rng(0)
    c = rng.random((30, 40, 3))
    c[:10, :, :2] = np.round(c[:10, :, :2] * 8) / 8  # exactly on the edges
    w = rng.random((30, 40))
    m = rng.random((30, 40)) > 0.3
    sel = m & (w > 0.3)
    ref = np.histogram2d(np.clip(c[sel, 0], 0, 0.999), np.clip(c[sel, 1], 0, 0.999), bins=8,
                         range=[[0, 1], [0, 1]])[0]
    np.testing.assert_array_equal(_chroma_hist((c, w), m), ref)
    assert _chroma_hist((c, w), np.zeros_like(m)).sum() == 0


def test_foot_of_an_added_object_at_its_support_depth_is_kept_and_its_shadow_is_not():
    """A box is added in front of the wall and a red foot reaches down from it onto the wall
    (at the wall's depth: no depth change, like the lowest part of an object standing on a
    table). The depth finds the box; the foot changed appearance only, and most of it lies
    within the two voxels around the box, but it reaches beyond them: it is a part of the
    object, not its rim, and is marked. The shadow the box casts, all of it within two voxels
    of the box, is not."""
    cams = [_wall_camera(x) for x in np.linspace(-1.0, 1.0, 9)]
    ids, frames, box, foot, shadow = {}, {}, {}, {}, {}
    for i, cam in enumerate(cams):
        z0, z1 = _box_scene_depth(cam, False), _box_scene_depth(cam, True)
        box[i] = z1 < 4.5
        P = world_points(z1, cam)
        foot[i] = ((np.abs(P[..., 0]) <= 0.6) & (P[..., 1] >= 0.6) & (P[..., 1] <= 1.25)
                   & ~box[i])
        shadow[i] = ((P[..., 0] >= -0.8) & (P[..., 0] < -0.6) & (P[..., 1] >= -0.6)
                     & (P[..., 1] <= 0.2) & ~box[i])
        rgb0, rgb1 = _wall_rgb(cam, z0), _wall_rgb(cam, z1, box[i] | foot[i])
        rgb1[shadow[i]] *= np.array([0.35, 0.4, 0.6], np.float32)
        for t, z, rgb in (("t0", z0, rgb0), ("t1", z1, rgb1)):
            ids[("p1", t, i)] = np.ones(z.shape, np.int32)
            frames[("p1", t, i)] = dict(depth=z, camera=cam, rgb=rgb)
    masks, _ = compare_paths(ids, frames, CompareOptions())
    for i in range(len(cams)):
        m1 = masks[("p1", i)][1]
        assert (m1 & box[i]).sum() > 0.75 * box[i].sum(), i
        assert (m1 & foot[i]).sum() > 0.5 * foot[i].sum(), (i, (m1 & foot[i]).sum())
        assert (m1 & shadow[i]).sum() <= 0.25 * shadow[i].sum(), i


def test_object_replaced_in_place_by_one_that_hides_it_is_a_change(caplog):
    """A flat ring lies on the floor at t0; at t1 a ball stands where it lay. From every pose
    the ball (a new ID at each pose, one object) hides the ring's middle; the rim left over
    shows the floor at t1 at a depth only
    2 % farther, within the depth tolerance, so no pose confirms the ring. Never seen at t1
    and hidden there by the ball (a change of t1) at every pose, it was replaced. An object
    that still stands behind a newcomer keeps its ID where it is not hidden; one that a change
    of light gave another ID at t1 shows that ID, of its own footprint, there; a piece of the
    floor beside the ball, which the ball half hides at t1, is smaller than the ball; and a
    floor patch re-segmented at t1 with nothing in front of it stays unchanged."""
    cam = _plane_camera(0.0)
    ids, frames = {}, {}
    for i in range(3):
        ids0, z0 = _blank()
        ids1, z1 = _blank()
        ids0[:], ids1[:] = 1, 1  # the floor at depth 5
        ids0[12:28, 8 + i:24 + i] = 5  # the ring at t0, 0.1 above the floor
        z0[12:28, 8 + i:24 + i] = 4.9
        ball = (7, 12, 13)[i]  # the ball at t1, in front of the ring's middle: one object,
        ids1[14:27, 10 + i:23 + i] = ball  # which the tracker gave another ID at each pose
        z1[14:27, 10 + i:23 + i] = 4.3
        ids0[8:12, 20 + i:26 + i] = 11  # a floor piece at t0 only, which the ball ...
        ids1[8:12, 20 + i:23 + i], z1[8:12, 20 + i:23 + i] = ball, 4.3  # ... half hides at t1
        ids0[5:35, 40:50] = ids1[5:35, 40:50] = 3  # a box that stays ...
        z0[5:35, 40:50] = z1[5:35, 40:50] = 4.5
        ids1[5:20, 38:52] = 8  # ... with a new object in front of its top at t1
        z1[5:20, 38:52] = 3.5
        ids0[30:38, 5:15] = 6  # a floor patch segmented apart at t0 only
        ids0[2:12, 28:36], z0[2:12, 28:36] = 9, 4.5  # a box the light change made ...
        ids1[2:12, 28:36], z1[2:12, 28:36] = 10, 4.5  # ... unrecognisable at t1 (ID 10)
        ids1[2:6, 27:37], z1[2:6, 27:37] = 8, 3.5  # the new object hides its top too
        for t, (m, z) in enumerate(((ids0, z0), (ids1, z1))):
            ids[("p1", f"t{t}", i)] = m
            frames[("p1", f"t{t}", i)] = dict(depth=z, camera=cam)
    o = CompareOptions(min_area=4, geometry=False, flat=False)
    with caplog.at_level("INFO", logger="gdiff.compare"):
        masks, df = compare_paths(ids, frames, o)
    df = df.set_index("id")
    assert df.loc[[7, 12, 13], "changed"].all() and (df.loc[[7, 12, 13], "type"] == "added").all()
    ball = df.loc[7, "instance"]
    assert ball in (7, 12, 13) and (df.loc[[7, 12, 13], "instance"] == ball).all()
    assert df.loc[8, "changed"] and df.loc[8, "type"] == "added"
    assert df.loc[5, "n_confirmed"] == 0  # no pose could confirm the ring by itself
    assert df.loc[5, "changed"] and df.loc[5, "type"] == "removed" and df.loc[5, "partner"] == ball
    assert df.loc[5, "instance"] == 5
    assert not df.loc[3, "changed"] and not df.loc[6, "changed"]
    assert not df.loc[9, "changed"]  # its other look shows where it is not hidden
    assert not df.loc[11, "changed"]  # hidden by the ball too, but a smaller piece beside it
    assert "replaced: 1 IDs" in caplog.text and f"5 by {ball}" in caplog.text
    cand = df.attrs["candidates"].set_index("instance")
    assert cand.loc[5, "verdict"] == f"kept: replaced by {ball}"
    m0, m1 = masks[("p1", 1)]
    assert m0[12:28, 9:25].all() and not m0[30:38, 5:15].any() and not m0[5:35, 40:50].any()
    # without the ball the ring's rim alone decides: unchanged
    for i in range(3):
        ids[("p1", "t1", i)][np.isin(ids[("p1", "t1", i)], (7, 12, 13))] = 1
        frames[("p1", "t1", i)]["depth"][8:27, 10 + i:23 + i] = 5.0
    _, df = compare_paths(ids, frames, o)
    assert not df.set_index("id").loc[5, "changed"]


def _replaced_table(hider_type: str) -> pd.DataFrame:
    """A ring (ID 5) seen at t0 only, at 10 poses, hidden at t1 at 8 of them by ID 7 of the
    changed object 7 (typed ``hider_type``) of its size and at its place."""
    df = pd.DataFrame([
        dict(id=5, changed=False, type="", partner=0, n_t0=10, n_t1=0, instance=0,
             x=0.0, y=0.0, z=5.0, size=0.7),
        dict(id=7, changed=True, type=hider_type, partner=0, n_t0=0, n_t1=10, instance=7,
             x=0.1, y=0.0, z=5.0, size=0.75)])
    df.attrs["hidden_by"] = {5: {7: 8}}
    return df


def test_replaced_counts_a_moved_hider_but_not_one_of_its_own_time():
    """The object in the ring's place at t1 may be typed moved (it stands at both times, or
    was paired with something elsewhere): it replaced the ring all the same. A removed object
    hides nothing at t1."""
    o = CompareOptions()
    for hider, marked in (("added", True), ("moved", True), ("removed", False)):
        df = _replaced_table(hider)
        assert (replaced(df, o) == [5]) is marked, hider
        assert bool(df.set_index("id").loc[5, "changed"]) is marked, hider


def test_receded_needs_the_rest_farther_than_the_pose_noise():
    """The rest of a hidden region counts as showing what stood behind it only when its depth
    at the other time grew by more than RECEDED_NOISE times the pose's depth noise; the noise
    is measured on the surfaces that stay with the same ID."""
    rng = np.random.default_rng(0)
    H, W = 40, 60
    ids = np.ones((H, W), np.int64)
    ids[10:30, 10:30] = 5  # the candidate at t0
    ids1 = ids.copy()
    ids1[10:30, 10:30] = 1  # ... gone at t1: the floor shows
    z0 = np.full((H, W), 5.0) * (1 + 0.01 * rng.standard_normal((H, W)))
    z1 = np.full((H, W), 5.0) * (1 + 0.01 * rng.standard_normal((H, W)))
    stay0 = stay1 = ids == 1
    noise = change_mod._depth_noise(ids, ids1, z0, z1, stay0, stay1, None)
    assert 0.005 < noise < 0.02  # median |N(0, sqrt(2) %)| ~ 0.95 %
    rest = ids == 5
    own = z0.copy()
    for rise, farther in ((0.0, False), (0.5 * noise, False), (4 * noise, True)):
        own[rest] = z1[rest] / (1 + rise)
        assert change_mod._receded(own, z1, rest, noise) is farther, rise
    assert not change_mod._receded(own, z1, rest, float("nan"))
    assert not change_mod._receded(own, z1, np.zeros((H, W), bool), noise)


def test_object_voxels_need_the_vote_two_frames_and_the_other_time_empty():
    """A voxel is an object's when at least ``vote`` of the frames with a surface in it flag
    it, at least two do, and most of those poses see no surface there at the other time; -1
    (no surface) is never a voxel."""
    from gdiff.compare.spread import (count_voxels, depth_edges, object_voxels, spread_masks,
                                      voxel_keys)

    keys = np.array([[1, 2, 3, -1]], np.int64)
    here = count_voxels([(keys, np.array([[True, True, False, True]])),
                         (keys, np.array([[True, False, False, False]])),
                         (keys, np.array([[False, False, False, False]]))])
    empty = count_voxels([])
    # voxel 1: flagged by 2 of 3 frames; voxel 2: by 1 of 3 (one frame is never enough)
    assert object_voxels(here, empty, 0.3).tolist() == [1]
    assert object_voxels(here, empty, 0.7).tolist() == []  # 2 of 3 is below 0.7
    assert object_voxels(here, empty, 0.3, min_views=1).tolist() == [1, 2]
    assert object_voxels(empty, empty, 0.3).tolist() == []
    # at the other time 2 of the 3 poses see a surface in voxel 1: it stayed, it is not carried
    other = count_voxels([(np.array([[1, -1]]), np.zeros((1, 2), bool))] * 2)
    assert object_voxels(here, other, 0.3).tolist() == []
    assert object_voxels(here, other, 0.3, vacated=0.7).tolist() == [1]  # 2 < 0.7 x 3
    m = spread_masks(np.array([[1, 2, -1, 5]], np.int64), np.array([1, 5], np.int64))
    assert m.tolist() == [[True, False, False, True]]
    # a depth step of 20 % at column 10: pixels within 2 columns of it are edges, a 1 % slope
    # is not; nor is a pixel without a surface a key
    z = np.tile(np.where(np.arange(20) < 10, 4.0, 5.0) * (1 + 0.0005 * np.arange(20)), (6, 1))
    edges = depth_edges(z, 0.05)
    assert np.flatnonzero(edges[3]).tolist() == [8, 9, 10, 11]
    z[0, 0] = np.nan
    cam = _wall_camera(0.0)
    assert voxel_keys(z, cam, 0.1)[0, 0] == -1 and voxel_keys(z, cam, 0.1)[3, 9] >= 0
    assert voxel_keys(z, cam, 0.1, edge_rel=0.05)[3, 9] == -1


def test_changed_object_merged_at_most_poses_is_carried_there_in_3d():
    """A box is added in front of the wall. The segmenter cuts it out at 4 of the 9 poses and
    merges it with the wall at the other 5, and at 3 poses its segment also takes a strip of
    the wall along. The ID comparison marks the box at its 4 poses only; carried in 3D, the box
    is marked at all 9. The strip is not carried: the wall there looks the same at both
    times."""
    cams = [_wall_camera(x) for x in np.linspace(-1.0, 1.0, 9)]
    ids, frames, truth, strip = {}, {}, {}, {}
    keys = {("p1", i): i % 2 for i in range(len(cams))}  # every pose a key frame of a time
    for i, cam in enumerate(cams):
        z0, z1 = _box_scene_depth(cam, False), _box_scene_depth(cam, True)
        truth[i] = z1 < 4.5
        P = world_points(z1, cam)
        strip[i] = (P[..., 0] >= -2.4) & (P[..., 0] <= -1.9) & ~truth[i]
        ids1 = np.ones(z1.shape, np.int32)
        if i < 4:
            ids1[truth[i]] = 3
        if i < 3:
            ids1[strip[i]] = 3
        for t, z, rgb, m in (("t0", z0, _wall_rgb(cam, z0), np.ones(z0.shape, np.int32)),
                             ("t1", z1, _wall_rgb(cam, z1, truth[i]), ids1)):
            ids[("p1", t, i)] = m
            frames[("p1", t, i)] = dict(depth=z, camera=cam, rgb=rgb)
    o = CompareOptions(geometry=False, flat=False)
    masks, df = compare_paths(ids, frames, o, keys=keys)
    assert set(df.loc[df["changed"], "id"]) == {3}
    for i in range(len(cams)):
        m0, m1 = masks[("p1", i)]
        assert not m0.any(), i
        hit = (m1 & truth[i]).sum() / truth[i].sum()
        assert hit > 0.7, (i, hit)  # less a depth edge 2 px wide around a 30 px box
        if i >= 3:
            assert not (m1 & strip[i]).any(), i
            assert (m1 & ~truth[i]).sum() <= 0.05 * truth[i].sum(), i
    off, _ = compare_paths(ids, frames, dataclasses.replace(o, spread_vote=0.0), keys=keys)
    assert all(not off[("p1", i)][1].any() for i in range(4, len(cams)))


def test_pair_scores_at_once_equal_the_pairwise_definitions():
    """_pair_moved and _group_instances score all pairs with arrays: the same as
    :func:`_apart` and :func:`_bhattacharyya` pair by pair, with missing positions (apart)
    and missing or empty histograms (0)."""
    from gdiff.compare.change import _apart, _apart_all, _bhattacharyya, _root_hists

    rng = np.random.default_rng(4)
    pos = [None if k % 7 == 0 else (rng.random(3 if k % 5 else 2) * 2, float(rng.random()))
           for k in range(40)]
    hists = [None if k % 9 == 0 else np.zeros((4, 4)) if k % 11 == 0 else rng.random((4, 4)) ** 4
             for k in range(40)]
    apart = _apart_all(pos[:25], pos[25:] + pos[:3])
    B = _root_hists(hists[:25]) @ _root_hists(hists[25:]).T
    for i in range(25):
        for j, q in enumerate(pos[25:] + pos[:3]):
            assert apart[i, j] == _apart(pos[i], q)
        for j in range(15):
            assert B[i, j] == pytest.approx(_bhattacharyya(hists[i], hists[25 + j]), abs=1e-12)
    assert apart.any() and (~apart).any() and (B > 0.5).any() and (B == 0).any()


def _textured(rng, h=120, w=160):
    """sRGB [h, w, 3]: a busy pattern (a patterned fabric) at the scale of a few pixels."""
    base = cv2.GaussianBlur(rng.random((h, w, 3)).astype(np.float32), (0, 0), 1.5)
    return np.clip(0.25 + 1.5 * (base - 0.5), 0.0, 1.0) * 0.6 + 0.2


def test_completion_grows_a_confirmed_piece_into_what_the_photo_shows():
    """A red can stands on patterned fabric in the photo; the other time's render shows the
    fabric alone, a pixel off (misaligned edges). The change mask has the can's top piece only.
    Grown, it covers the can and barely more; a piece of the mask on the fabric, which the
    photo shows as the other time does, does not grow; nor does any piece when asked not to;
    a far reach stays on the can."""
    from gdiff.compare.complete import difference, grow_pieces, noise_floor

    rng = np.random.default_rng(0)
    fabric = _textured(rng)
    yy, xx = np.mgrid[:120, :160]
    can = (np.abs(xx - 80) <= 10) & (yy >= 20) & (yy <= 100)
    photo = fabric.copy()
    photo[can] = (0.75, 0.08, 0.1)
    other = np.roll(fabric, 1, axis=1)  # the other time: fabric only, a pixel off
    own = cv2.GaussianBlur(photo, (0, 0), 1.2)  # the fit's own render: blurred
    d_other = difference(photo, other)
    floor = noise_floor(d_other, difference(photo, own))
    top = can & (yy <= 60)  # its upper half
    false = (np.abs(xx - 30) <= 6) & (np.abs(yy - 60) <= 6)
    grown, n = grow_pieces(top | false, d_other, floor, reach=1.0)
    assert n == 1
    assert (grown & can).sum() > 0.95 * can.sum()
    rim = cv2.dilate(can.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    assert not (grown & ~rim & ~false).any()
    assert np.array_equal(grown & false, false) and not (grown & ~false & ~rim).any()
    assert np.array_equal(grow_pieces(top, d_other, floor, reach=0.0)[0], top)
    far, _ = grow_pieces(top, d_other, floor, reach=5.0)
    assert not (far & ~rim).any()
    hidden = np.ones_like(can)  # pixels where a render shows no surface are never added
    hidden[60:, :] = False
    part, _ = grow_pieces(top, d_other, floor, reach=1.0, valid=hidden)
    assert not (part & ~top)[60:].any() and (part & can)[:60].sum() > 0.9 * can[:60].sum()


def test_completion_leaves_to_the_other_time_what_its_change_explains():
    """A before key view: a red can was taken away (its top piece is in the t0 mask) and a
    blue box put down right next to it (in the t1 mask, the other time's render at this pose
    shows it). The before photo differs from that render over both; completing the t0 mask
    covers the can but not the box: the photo differs there because of the other time's
    change, and the partition would learn the fabric under it as changed at t0."""
    from gdiff.compare.complete import complete_key_masks, difference, grow_pieces, noise_floor

    rng = np.random.default_rng(1)
    fabric = _textured(rng)
    yy, xx = np.mgrid[:120, :160]
    can = (np.abs(xx - 70) <= 10) & (yy >= 20) & (yy <= 100)
    box = (xx >= 81) & (xx <= 110) & (yy >= 40) & (yy <= 100)
    photo = fabric.copy()
    photo[can] = (0.75, 0.08, 0.1)  # before: the can, and fabric where the box will be
    other = np.roll(fabric, 1, axis=1)  # after: fabric where the can stood, and the box
    other[box] = (0.1, 0.15, 0.8)
    own = cv2.GaussianBlur(photo, (0, 0), 1.2)
    d_other = difference(photo, other)
    floor = noise_floor(d_other, difference(photo, own))
    top = can & (yy <= 60)
    frames = {("p", "t0", 0): {"rgb": own}, ("p", "t1", 0): {"rgb": other}}
    masks = {("p", 0): (top.copy(), box.copy())}
    done, n, added = complete_key_masks(masks, frames.get, {("p", 0): 0},
                                        {("p", 0): (d_other, floor)}, reach=1.0, alpha_min=0.5)
    m0, m1 = masks[("p", 0)]
    assert (done, n) == (1, 1) and added > 0
    assert (m0 & can).sum() > 0.95 * can.sum()
    assert not (m0 & box).any() and np.array_equal(m1, box)
    # the same growth without the other time's mask runs into the box
    free, _ = grow_pieces(top, d_other, floor, reach=1.0)
    assert (free & box).sum() > 0.5 * box.sum()


def test_completion_joins_the_fragments_of_an_object_and_fills_its_print():
    """A red box with a printed label (dots of the fabric's colours) is added on patterned
    fabric; the segmenter left only specks of it in the mask, a few pixels apart. Grown, the
    specks act as one piece, whose size sets the reach: the box is covered whole, its print
    too, and barely more. Each speck alone (the others removed) reaches only its own size."""
    from gdiff.compare.complete import _disc, difference, grow_pieces, noise_floor

    rng = np.random.default_rng(2)
    h, w = 480, 640
    fabric = _textured(rng, h, w)
    yy, xx = np.mgrid[:h, :w]
    box = (np.abs(xx - 320) <= 20) & (yy >= 200) & (yy <= 260)
    photo = fabric.copy()
    photo[box] = (0.7, 0.1, 0.12)
    other = np.roll(fabric, 1, axis=1)  # the other time: fabric only, a pixel off
    dots = box & (yy % 8 < 3) & (xx % 8 < 3)  # the print: the other render's colours there
    photo[dots] = other[dots]
    d_other = difference(photo, other)
    floor = noise_floor(d_other, difference(photo, cv2.GaussianBlur(photo, (0, 0), 1.2)))
    gap = _disc((h, w)).shape[0] // 2  # closer than the disc's span: one object's fragments
    specks = np.zeros_like(box)
    for y in range(218, 246, gap + 3):
        specks[y:y + 3, 319:322] = True
    assert (specks & box).sum() == specks.sum() and specks.sum() >= 3 * 9
    grown, n = grow_pieces(specks, d_other, floor, reach=1.0)
    assert n == 1
    assert (grown & box).sum() > 0.95 * box.sum()  # the print's dots filled
    rim = cv2.dilate(box.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    assert not (grown & ~rim).any()
    one = specks & (yy < 225)
    alone, _ = grow_pieces(one, d_other, floor, reach=1.0)
    assert (alone & box).sum() < 0.2 * box.sum()


def test_completion_floor_follows_a_render_that_is_off_everywhere():
    """At a pose the other time's photos saw poorly, its render differs from the photo all
    over (blotches of wrong colour). The floor rises above that: a piece of the mask on the
    wall is not confirmed there and does not spread into the blotches, while a piece of a
    real change grows over its object and not beyond. Another exposure of the other render
    (auto exposure) leaves the floor low."""
    from gdiff.compare.complete import difference, grow_pieces, noise_floor

    rng = np.random.default_rng(1)
    wall = _textured(rng)
    yy, xx = np.mgrid[:120, :160]
    cup = (xx - 100) ** 2 + (yy - 60) ** 2 <= 15 ** 2
    photo = wall.copy()
    photo[cup] = (0.95, 0.85, 0.1)
    blotches = cv2.GaussianBlur(rng.normal(0, 1, (120, 160)).astype(np.float32), (0, 0), 4)
    blotches *= 0.2 / blotches.std()
    other = np.clip(wall + blotches[..., None] * (1.0, 0.8, 0.6), 0, 1).astype(np.float32)
    d = difference(photo, other)
    own = cv2.GaussianBlur(photo, (0, 0), 1.2)
    floor = noise_floor(d, difference(photo, own))
    assert floor > np.percentile(d[~cup], 80)
    false = (np.abs(xx - 35) <= 8) & (np.abs(yy - 60) <= 8)
    grown, n = grow_pieces((cup & (xx <= 100)) | false, d, floor, reach=1.0)
    assert n == 1 and (grown & cup).sum() > 0.9 * cup.sum()
    ring = cv2.dilate(cup.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    assert not (grown & ~ring & ~false).any()
    low = np.percentile(difference(photo, own), 99)  # the fit's own error alone: it spreads
    assert (grow_pieces(false, d, low, reach=1.0)[0] & ~false).sum() > false.sum()
    dark = difference(photo, wall * 0.5)  # another exposure, nothing else
    assert noise_floor(dark, difference(photo, own)) < 0.1 < np.median(dark[cup])


def _box_added_in_pieces(light_bars: bool = False, noisy: bool = True):
    """Nine poses before the wall; a red box is added at t1. The fit renders its lower half
    a little transparent, at a depth of its own, and the segmenter merges that half into the wall:
    the ID comparison sees the upper half. ``noisy``: the lower half's depth differs from pose
    to pose (a sparse capture: no two photos agree on it), else it is the wall's at every pose.
    The key frames (odd poses: t1, even: t0) have photos: the box whole at t1. ``light_bars``:
    at t1 the shadow bars of blinds fall across the scene (a change of light), in the renders
    and the photos. Returns (ids, frames, keys, photos, box masks per pose)."""
    cams = [_wall_camera(x) for x in np.linspace(-1.0, 1.0, 9)]
    keys = {("p1", i): i % 2 for i in range(len(cams))}
    ids, frames, photos, box = {}, {}, {}, {}
    for i, cam in enumerate(cams):
        z_box = _box_scene_depth(cam, True)
        wall_z, x, y, _ = _wall_poster(cam)
        box[i] = z_box < 4.5
        upper = box[i].copy()
        upper[60:] = False  # y >= 0: the lower half
        z1 = np.where(upper, z_box, wall_z)
        lower = box[i] & ~upper
        if noisy:
            z1[lower] = 1.5 + 0.25 * i  # in front of the box, never twice the same
        rgb0 = _wall_rgb(cam, wall_z)
        rgb1 = _wall_rgb(cam, wall_z, upper)
        rgb1[lower] = 0.3 * rgb1[lower] + 0.7 * np.array((0.8, 0.1, 0.1), np.float32)
        full = _wall_rgb(cam, z_box, box[i])
        if light_bars:
            bars = (np.sin(6 * (x + y)) > 0) & (np.abs(y - 0.8) <= 0.6)  # below the box's top
            shade = np.where(bars, 0.35, 1.0).astype(np.float32)[..., None]
            rgb1, full = rgb1 * shade, full * shade
        photos[("p1", i)] = srgb_to_linear(full if keys[("p1", i)] == 1 else rgb0)
        ids1 = np.ones(wall_z.shape, np.int32)
        ids1[upper] = 2
        ids[("p1", "t0", i)], ids[("p1", "t1", i)] = np.ones(wall_z.shape, np.int32), ids1
        frames[("p1", "t0", i)] = dict(depth=wall_z, camera=cam, rgb=rgb0)
        frames[("p1", "t1", i)] = dict(depth=z1, camera=cam, rgb=rgb1)
    return ids, frames, keys, photos, box


def test_key_view_masks_are_completed_from_the_training_photos():
    """The box added in pieces (:func:`_box_added_in_pieces`), its lower half's depth not
    trusted: the key frames of t1 mark it whole, from their photos; the other poses (no photo)
    keep the IDs' mask, and so does every pose with completion off or without photos. Where
    the depth is trusted at both times, the IDs' masks are kept as they are."""
    ids, frames, keys, photos, box = _box_added_in_pieces()
    # a sparse capture: no surface is seen by enough photos for its depth to be trusted
    o = CompareOptions(observed_min_views=20, geometry=False, flat=False, spread_vote=0.0)
    masks, df = compare_paths(ids, frames, o, keys=keys, photos=photos)
    assert df.set_index("id").at[2, "changed"]
    plain, _ = compare_paths(ids, frames, dataclasses.replace(o, complete_reach=0.0),
                             keys=keys, photos=photos)
    no_photos, _ = compare_paths(ids, frames, o, keys=keys)
    for i in range(len(box)):
        m0, m1 = masks[("p1", i)]
        share = (m1 & box[i]).sum() / box[i].sum()
        ring = cv2.dilate(box[i].astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        assert not m0.any() and not (m1 & ~ring).any()
        assert np.array_equal(no_photos[("p1", i)][1], plain[("p1", i)][1])
        plain_share = (plain[("p1", i)][1] & box[i]).sum() / box[i].sum()
        assert plain_share < 0.6
        if keys[("p1", i)] == 1:
            assert share > 0.95, (i, share)
        else:
            assert np.array_equal(m1, plain[("p1", i)][1])
    # the lower half's depth agreed on by the photos: trusted, so the IDs' masks stay as
    # they are (what a photo shows differently beside them is taken for a shadow or for the
    # other time's object)
    ids, frames, keys, photos, box = _box_added_in_pieces(noisy=False)
    dense = dataclasses.replace(o, observed_min_views=2, observed_min_parallax=0.0)
    masks, _ = compare_paths(ids, frames, dense, keys=keys, photos=photos)
    plain, _ = compare_paths(ids, frames, dataclasses.replace(dense, complete_reach=0.0),
                             keys=keys, photos=photos)
    assert all(np.array_equal(a, b) for k in masks for a, b in zip(masks[k], plain[k]))


def test_key_view_masks_are_not_completed_under_a_change_of_light():
    """The same box, with the shadow bars of blinds across the scene at t1: the photos of t1
    differ from the t0 renders wherever the bars fall, so they no longer outline the box. The
    flat evidence takes it for a change of light, and the key frames keep the IDs' masks (grown,
    the box's pieces would spread into the bars beside it)."""
    ids, frames, keys, photos, box = _box_added_in_pieces(light_bars=True)
    o = CompareOptions(observed_min_views=2, observed_min_parallax=0.0, spread_vote=0.0)
    masks, df = compare_paths(ids, frames, o, keys=keys, photos=photos)
    plain, _ = compare_paths(ids, frames, dataclasses.replace(o, complete_reach=0.0),
                             keys=keys, photos=photos)
    assert df.set_index("id").at[2, "changed"]
    for k in masks:
        assert all(np.array_equal(a, b) for a, b in zip(masks[k], plain[k]))


def test_photo_confirms_an_object_that_neither_depth_nor_colour_can():
    """A sparse capture: a dark grey mug is put on a light grey table. The fit drew it where
    the table is (no 3D evidence) and its chromaticity relative to the table is the table's
    (no colour evidence). The training photos of the after visit show it where the before
    render shows table, and those of the before visit show table where the after render shows
    the mug: it is kept by the photos. A piece of table the segmenter cut differently at t1
    looks in the photos of both visits as the other time renders it: dropped. So is a piece
    the before model renders wrongly at the after poses (it never saw it from there): the after
    photos differ from that render, but the before photos show it as the after model renders
    it. Not kept when seen at one pose only, nor when the light changed, nor with
    confirm_photo 0 (off), nor without photos of the before visit, nor where no photo
    of the before visit shows the surface."""
    from gdiff.compare.complete import key_differences

    rng = np.random.default_rng(0)
    h, w = 120, 160
    table = np.full((h, w, 3), 0.7, np.float32) + rng.normal(0, 0.02, (h, w, 1)).astype(np.float32)
    mug = np.zeros((h, w), bool)
    mug[40:80, 60:90] = True
    piece = np.zeros((h, w), bool)
    piece[10:30, 10:50] = True
    poor = np.zeros((h, w), bool)
    poor[90:115, 100:150] = True
    after = table.copy()
    after[mug] = 0.25  # grey: the same chromaticity as the table
    keys, frames, photos, ids = {}, {}, {}, {}
    for i in range(6):
        t = int(i < 3)  # poses 0-2: after photos, 3-5: before photos
        before = table.copy()
        if t == 1:
            before[poor] = 0.35  # the before model's guess where its photos never looked
        frames[("p2", "t0", i)] = dict(rgb=before)
        frames[("p2", "t1", i)] = dict(rgb=after)
        noise = rng.normal(0, 0.01, (h, w, 3)).astype(np.float32)
        photos[("p2", i)] = srgb_to_linear(np.clip((after if t else table) + noise, 0, 1))
        keys[("p2", i)] = t
        ids1 = np.ones((h, w), np.int32)
        ids1[mug], ids1[piece], ids1[poor] = 3, 2, 4
        ids[("p2", "t0", i)] = np.ones((h, w), np.int32)
        ids[("p2", "t1", i)] = ids1
    diffs = key_differences(frames.get, keys, photos)
    assert set(diffs) == set(keys)

    def judged(n_confirmed=3, light_changed=False, diffs=diffs, **kw):
        o = CompareOptions(**{"confirm_photo": 2.0, **kw})
        df = pd.DataFrame(dict(id=[1, 2, 3, 4], changed=[False, True, True, True],
                               type=["", "added", "added", "added"], instance=[0, 2, 3, 4],
                               place=[0, 2, 3, 4], partner=[0, 0, 0, 0],
                               colour=[np.nan, 0.01, 0.02, 0.01], n_colour=[0, 3, 3, 3],
                               n_t0=[6, 0, 0, 0], n_t1=[6, 6, 6, 6],
                               n_confirmed=[0, 3, n_confirmed, 3], area=[1.0, 800, 1200, 1250],
                               support=[np.nan, 0.0, 0.0, 0.0],
                               **{c: [0.0] * 4 for c in ("x", "y", "z", "size")}))
        cmp_stage._photo_support(df, ids, keys, diffs, o.confirm_photo, o.min_area)
        cmp_stage._confirm_by_evidence(df, o, 8, light_changed)
        return df, df.attrs["candidates"].set_index("instance")

    df, cand = judged()
    assert cand.loc[3, ["photo", "photo_other"]].min() > 0.9
    assert cand.loc[3, "verdict"] == "kept: photo"
    assert cand.loc[2, ["photo", "photo_other"]].max() < 0.1 and cand.loc[2, "verdict"] == "dropped"
    assert cand.loc[4, "photo"] > 0.9 and cand.loc[4, "photo_other"] < 0.1
    assert cand.loc[4, "verdict"] == "dropped"
    assert set(df.loc[df["changed"], "id"]) == {3}
    after_only = {k: v for k, v in diffs.items() if keys[k] == 1}
    for kw in (dict(n_confirmed=1), dict(light_changed=True), dict(confirm_photo=0.0),
               dict(diffs=after_only)):
        df, cand = judged(**kw)
        assert not df["changed"].any() and cand.loc[3, "verdict"] == "dropped", kw
    # where the before photos did not see the table, the before render there is a guess
    unseen = {k: ~mug for k in keys}
    df = pd.DataFrame(dict(id=[3], changed=[True], type=["added"], instance=[3], place=[3],
                           n_confirmed=[3]))
    cmp_stage._photo_support(df, ids, keys, diffs, 2.0, 24, unseen)
    assert np.isnan(df.loc[0, "photo"]) and np.isnan(df.loc[0, "photo_other"])
    cmp_stage._photo_support(df, ids, keys, diffs, 2.0, 24, None)
    assert df.loc[0, ["photo", "photo_other"]].min() > 0.9


def test_every_ids_chroma_histogram_at_once_is_each_ids_own():
    """The per-pose histograms of all IDs (one pass) equal the per-ID ones."""
    from gdiff.compare.change import _chroma_hist, _id_chroma_hists, _normalised_chroma

    rng = np.random.default_rng(3)
    rgb = rng.random((40, 50, 3)).astype(np.float32)
    rgb[:10] *= 0.05  # dark rows: below the confidence cut
    ids = rng.integers(0, 7, (40, 50)).astype(np.uint16)
    pair = _normalised_chroma(rgb)
    every = _id_chroma_hists(ids, pair)
    assert every.shape == (7, 8, 8)
    for i in range(1, 7):
        np.testing.assert_array_equal(every[i], _chroma_hist(pair, ids == i))
    assert every[0].sum() == 0  # ID 0 (no instance) is not counted


@pytest.mark.parametrize("width", [1, 2, 5, 13, 32])
def test_disc_dilation_by_rows_is_opencvs(width):
    from gdiff.compare.change import _dilate_disc

    rng = np.random.default_rng(width)
    mask = rng.random((70, 90)) < 0.01
    mask[0, 0] = mask[-1, 40] = mask[30, -1] = True  # at the borders
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * width + 1, 2 * width + 1))
    expected = cv2.dilate(mask.astype(np.uint8), kernel) > 0
    np.testing.assert_array_equal(_dilate_disc(mask, width), expected)
