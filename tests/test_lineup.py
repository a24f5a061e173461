"""Whether the t0 and t1 renders of a pose line up (gdiff.compare.lineup), and the stage's
report of it (coverage.csv, the log)."""

import dataclasses
import logging

import numpy as np
import pandas as pd
import pytest

from gdiff import synth
from gdiff.compare.lineup import poorly_lined_up, render_lineup
from gdiff.compare.stage import lineup_table, report_lineup, unlined_poses


def _turned(cam, deg):
    """The camera turned by ``deg`` about its own y axis (camera-to-world composed)."""
    a = np.deg2rad(deg)
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    c2w = cam.c2w.copy()
    c2w[:3, :3] = c2w[:3, :3] @ R
    return cam.with_pose(c2w)


@pytest.fixture(scope="module")
def views():
    p = dataclasses.replace(synth.get_preset("demo"), width=240, height=180, supersample=1)
    scene = synth.build_scene(p, 0)
    cams = synth.orbit_path(scene, "before", 3)
    return scene, cams


def test_renders_of_one_pose_line_up_whatever_changed(views):
    scene, cams = views
    cam = cams[0]
    rgb0 = scene.render(cam, "before")["rgb"]
    rgb1 = scene.render(cam, "after")["rgb"]  # objects added and removed
    same = render_lineup(rgb0, rgb1)
    assert same.matches >= 20 and same.in_place > 0.8
    # auto exposure: one stop darker at t1 moves no feature
    dark = render_lineup(rgb0, np.clip(rgb1 * 0.5, 0, 1))
    assert dark.in_place > 0.8
    # the t1 model drawn as from a camera turned by 3 degrees (a photo placed off)
    off = render_lineup(rgb0, scene.render(_turned(cam, 3.0), "after")["rgb"])
    assert off.in_place < 0.2
    # nothing to match
    blank = render_lineup(np.zeros_like(rgb0), np.zeros_like(rgb0))
    assert blank.matches == 0 and np.isnan(blank.in_place)
    with pytest.raises(ValueError, match="differ in size"):
        render_lineup(rgb0, rgb0[:-1])


def test_poses_below_the_scenes_median_are_named():
    x = np.array([0.9, 0.95, 0.85, 0.1, np.nan])
    assert poorly_lined_up(x, 0.5).tolist() == [False, False, False, True, True]
    assert not poorly_lined_up(x, 0).any()
    assert not poorly_lined_up(np.full(3, np.nan), 0.5).any()
    # the scene is its own measure: a scene with few features in place everywhere is not named
    assert not poorly_lined_up(np.array([0.3, 0.35, 0.25]), 0.5).any()


def test_lineup_table_names_the_pose_whose_renders_do_not_line_up(views, caplog):
    scene, cams = views
    frames, keys, meta = {}, {}, {"p1": [dict(image=f"before/{k:03d}.png") for k in range(3)]}
    for k, cam in enumerate(cams):
        frames[("p1", "t0", k)] = dict(rgb=scene.render(cam, "before")["rgb"])
        c1 = _turned(cam, 4.0) if k == 1 else cam
        frames[("p1", "t1", k)] = dict(rgb=scene.render(c1, "after")["rgb"])
        keys[("p1", k)] = 0
    df = lineup_table(frames.get, keys, meta, 0.5)
    assert df["lined_up"].tolist() == [True, False, True]
    assert (df["lineup_matches"] > 0).all()
    assert unlined_poses(df) == {"p1/00001"}  # named as the changes table names poses
    with caplog.at_level(logging.INFO, logger="gdiff.compare"):
        report_lineup(df, 0.5)
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1 and "before/001.png" in warned[0] and "before/000.png" not in warned[0]
    # under a change of light moved shadows move features too: the log says so
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="gdiff.compare"):
        report_lineup(df, 0.5, light_changed=True)
    assert any("light changed" in r.getMessage() for r in caplog.records
               if r.levelno == logging.WARNING)
    # off: no pose judged
    off = lineup_table(frames.get, keys, meta, 0)
    assert off["lined_up"].isna().all() and unlined_poses(off) == set()


def test_colour_seen_changed_at_one_pose_that_does_not_line_up_does_not_keep_an_object(views):
    """Three key poses of a synthetic scene; at the middle one the t0 model is drawn as from a
    camera turned by 4 degrees, so its two renders do not line up. Six objects changed colour
    against their surroundings: one the ID comparison found at that pose only (dropped), one at
    a pose that lines up (kept), one at two poses (kept), one found at that pose only but whose
    shape changed in 3D (kept), one found at that pose only whose photo there shows it changed
    (kept), and one in two pieces, each found at one pose, at two poses (kept). Under a change
    of light, or with the rule off, colour keeps the first too."""
    from gdiff.compare.change import CompareOptions
    from gdiff.compare.stage import _confirm_by_evidence

    scene, cams = views
    frames, keys, meta = {}, {}, {"p1": [dict(image=f"after/{k:03d}.png") for k in range(3)]}
    for k, cam in enumerate(cams):
        frames[("p1", "t0", k)] = dict(rgb=scene.render(_turned(cam, 4.0) if k == 1 else cam,
                                                        "before")["rgb"])
        frames[("p1", "t1", k)] = dict(rgb=scene.render(cam, "after")["rgb"])
        keys[("p1", k)] = 1
    unlined = unlined_poses(lineup_table(frames.get, keys, meta, 0.5))
    assert unlined == {"p1/00001"}

    def verdicts(light_changed=False, unlined=unlined, **kw):
        n = 8
        df = pd.DataFrame(dict(
            id=[1, 2, 3, 4, 5, 6, 7, 8], changed=[False] + [True] * 7,
            type=[""] + ["added"] * 7, instance=[0, 2, 3, 4, 5, 6, 7, 7],
            place=[0, 2, 3, 4, 5, 6, 7, 7], partner=[0] * n,
            colour=[np.nan, 0.6, 0.6, 0.6, 0.1, 0.6, 0.6, 0.6],
            n_colour=[0, 1, 1, 2, 1, 1, 1, 1], n_t0=[3, 0, 0, 0, 0, 0, 0, 0],
            n_t1=[3, 1, 1, 2, 1, 1, 1, 1], n_confirmed=[0, 1, 1, 2, 1, 1, 1, 1],
            first=["p1/00000", "p1/00001", "p1/00000", "p1/00001", "p1/00001", "p1/00001",
                   "p1/00001", "p1/00002"],
            last=["p1/00002", "p1/00001", "p1/00000", "p1/00002", "p1/00001", "p1/00001",
                  "p1/00001", "p1/00002"],
            photo=[np.nan, 0.0, 0.0, 0.0, 0.0, 0.9, 0.0, 0.0],
            area=[1.0] + [300.0] * 7, support=[np.nan, 0.0, 0.0, 0.0, 0.9, 0.0, 0.0, 0.0],
            **{c: [0.0] * n for c in ("x", "y", "z", "size")}))
        _confirm_by_evidence(df, CompareOptions(**kw), 8, light_changed, unlined)
        return df.attrs["candidates"].set_index("instance")["verdict"].to_dict()

    assert verdicts() == {2: "dropped", 3: "kept: colour", 4: "kept: colour", 5: "kept: 3D",
                          6: "kept: colour", 7: "kept: colour"}
    # an object whose two pieces show at two poses (one each) is found at two poses, even
    # where neither of them lines up
    assert verdicts(unlined=unlined | {"p1/00002"})[7] == "kept: colour"
    assert verdicts(light_changed=True)[2] == "kept: colour"
    assert verdicts(confirm_colour_lined_up=False)[2] == "kept: colour"
