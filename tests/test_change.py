"""ID comparison: change types (added / removed / moved), evidence check, masks, stage files."""

import dataclasses
import json

import numpy as np
import pandas as pd
import pytest

from gdiff import synth
from gdiff.change import CompareOptions, change_masks, decide, detect_changes_pair, pose_stats
from gdiff.io import read_ids, read_mask, srgb_to_linear
from gdiff.segment import SegmentOptions, make_segmenter
from gdiff.segtrack import compare, compare_paths, segment_and_track, track_paths
from gdiff.track import TrackOptions

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
    p = dataclasses.replace(synth.get_preset("demo"), width=128, height=96, supersample=1)
    scene = synth.build_scene(p, 2)
    frames, gt = {}, {}
    for i, cam in enumerate(synth.orbit_path(scene, "before", 6)):
        for t, st in (("t0", "before"), ("t1", "after")):
            r = scene.render(cam, st)
            frames[("p1", t, i)] = dict(rgb=r["rgb"], depth=r["depth"], camera=cam)
            gt[("p1", t, i)] = r
    return scene, frames, gt


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


def test_stage_files(demo_paths, tmp_path):
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
    assert (res / "instances" / "overlay" / "p1" / "t0" / "00000.jpg").exists()
    assert set(pd.read_csv(res / "instances" / "tracks.csv").columns) >= {"id", "first", "last"}
    summary = compare(res / "instances", res / "sequence" / "poses.json", res / "change",
                      CompareOptions())
    assert summary["changed"] >= 1
    kf = pd.read_csv(res / "change" / "keyframes.csv")
    assert list(kf.columns) == ["path", "frame", "image", "set", "time", "mask_t0", "mask_t1",
                                "mask_union"]
    assert list(kf["frame"]) == [0, 3] and (kf["time"] == 0).all()
    m = read_mask(res / kf["mask_union"].iloc[1])
    assert m.any() and (m == (read_mask(res / kf["mask_t0"].iloc[1])
                              | read_mask(res / kf["mask_t1"].iloc[1]))).all()
    ch = pd.read_csv(res / "change" / "changes.csv")
    assert set(ch["type"]) <= {"added", "removed", "moved"} and len(ch) == summary["changed"]
