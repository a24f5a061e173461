"""Pose interpolation: slerp/lerp, frame counts, separate paths, reordering."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from gdiff.cameras import Camera, look_at, save_cameras
from gdiff.errors import ConfigError, SceneError
from gdiff.interpolate import (InterpolateOptions, build_sequence, interpolate_pair,
                               load_sequence, short_path, slerp, step_costs)
from gdiff.options import from_config


def _orbit(n, set_, radius=2.0, height=1.0, span=(0.0, 120.0), phase=0.0, seed=0):
    """Cameras on an arc around the origin, looking at it, in capture order."""
    rng = np.random.default_rng(seed)
    cams = []
    for i, a in enumerate(np.radians(np.linspace(*span, n)) + np.radians(phase)):
        c = np.array([radius * np.cos(a), radius * np.sin(a), height]) + rng.normal(0, 0.01, 3)
        cams.append(Camera(64, 48, 60.0, 60.0, 32.0, 24.0, look_at(c, [0, 0, 0.2]),
                           image=f"{set_}/{i:03d}.png", set=set_,
                           time=0 if set_ == "before" else 1))
    return cams


def _paper_slerp(q0, q1, d):
    """The paper's formula literally (after choosing the shorter arc)."""
    if q0 @ q1 < 0:
        q1 = -q1
    th = np.arccos(np.clip(q0 @ q1, -1, 1))
    return np.sin((1 - d) * th) / np.sin(th) * q0 + np.sin(d * th) / np.sin(th) * q1


def _same_rotation(qa, qb, atol=1e-9):
    return np.allclose(qa, qb, atol=atol) or np.allclose(qa, -qb, atol=atol)


# ------------------------------------------------------------------ slerp


@pytest.mark.parametrize("seed", range(5))
def test_slerp_matches_scipy_and_paper_formula(seed):
    rng = np.random.default_rng(seed)
    q0, q1 = Rotation.random(2, random_state=seed).as_quat()
    deltas = np.sort(rng.random(7))
    ours = slerp(q0, q1, deltas)
    ref = Slerp([0, 1], Rotation.from_quat([q0, q1]))(deltas).as_quat()
    for a, b in zip(ours, ref):
        assert _same_rotation(a, b)
    for d, a in zip(deltas, ours):
        assert np.allclose(a, _paper_slerp(q0, q1, d), atol=1e-12)
    assert np.allclose(np.linalg.norm(ours, axis=1), 1.0)
    # constant angular speed: equal steps in delta give equal rotation angles
    qs = slerp(q0, q1, np.linspace(0, 1, 6))
    steps = [(Rotation.from_quat(qs[k]).inv() * Rotation.from_quat(qs[k + 1])).magnitude()
             for k in range(5)]
    assert np.allclose(steps, steps[0], atol=1e-9)


def test_slerp_endpoints_and_scalar():
    q0, q1 = Rotation.random(2, random_state=11).as_quat()
    assert _same_rotation(slerp(q0, q1, 0.0), q0)
    assert _same_rotation(slerp(q0, q1, 1.0), q1)
    assert slerp(q0, q1, 0.3).shape == (4,)


def test_slerp_double_cover_takes_shorter_arc():
    q0 = Rotation.from_rotvec([0, 0, 0.2]).as_quat()
    q1 = Rotation.from_rotvec([0, 0, 0.6]).as_quat()
    a = slerp(q0, q1, 0.5)
    b = slerp(q0, -q1, 0.5)  # -q1 is the same rotation
    assert _same_rotation(a, b, atol=1e-12)
    assert Rotation.from_quat(b).as_rotvec() == pytest.approx([0, 0, 0.4])
    # without the sign flip the naive formula would go the long way round (through 180+ deg)
    th = np.arccos(q0 @ -q1)
    naive = (np.sin(0.5 * th) * q0 + np.sin(0.5 * th) * -q1) / np.sin(th)
    assert not _same_rotation(naive / np.linalg.norm(naive), a, atol=1e-3)


def test_slerp_near_identical_quaternions():
    q0 = Rotation.from_rotvec([0.1, 0.2, 0.3]).as_quat()
    for eps in (0.0, 1e-12, 1e-9, 1e-7):
        q1 = Rotation.from_rotvec([0.1, 0.2, 0.3 + eps]).as_quat()
        q = slerp(q0, q1, np.array([0.25, 0.5, 0.75]))
        assert np.isfinite(q).all()
        assert np.allclose(np.linalg.norm(q, axis=1), 1.0)
        want = Rotation.from_rotvec([[0.1, 0.2, 0.3 + d * eps] for d in (0.25, 0.5, 0.75)])
        for a, b in zip(q, want.as_quat()):
            assert _same_rotation(a, b, atol=1e-9)
    # and with the opposite sign (q vs -q of the same rotation)
    q = slerp(q0, -q0, 0.5)
    assert _same_rotation(q, q0, atol=1e-12)


# ------------------------------------------------------------------ pairs and paths


def test_interpolate_pair_lerps_centres_not_translations():
    a, b = _orbit(2, "before", span=(0, 90))
    mids = interpolate_pair(a, b, 3)
    assert len(mids) == 3
    for j, c in enumerate(mids, 1):
        d = j / 4
        assert np.allclose(c.center, (1 - d) * a.center + d * b.center)
        qa = Rotation.from_matrix(a.c2w[:3, :3]).as_quat()
        qb = Rotation.from_matrix(b.c2w[:3, :3]).as_quat()
        want = Slerp([0, 1], Rotation.from_quat([qa, qb]))([d]).as_matrix()[0]
        assert np.allclose(c.c2w[:3, :3], want, atol=1e-9)
        assert c.image is None and c.set == "before"
        # the w2c translation is NOT the lerp of the key translations (it is -R^T C)
        t_lerp = (1 - d) * a.w2c[:3, 3] + d * b.w2c[:3, 3]
        assert not np.allclose(c.w2c[:3, 3], t_lerp, atol=1e-3)


@pytest.mark.parametrize("n", [0, 1, 4])
def test_build_sequence_counts_and_separate_paths(tmp_path, n):
    before, after = _orbit(7, "before"), _orbit(5, "after", phase=20, radius=2.3)
    ev = _orbit(2, "eval_before", phase=50)
    save_cameras(tmp_path / "cameras.json", before + ev + after)
    summary = build_sequence(tmp_path / "cameras.json", tmp_path / "seq" / "poses.json",
                             InterpolateOptions(n=n, max_angle_deg=None, max_step=None))
    assert summary["p1"]["frames"] == 7 + 6 * n and summary["p2"]["frames"] == 5 + 4 * n
    data = json.loads((tmp_path / "seq" / "poses.json").read_text())
    assert data["paths"]["p1"]["set"] == "before" and data["paths"]["p2"]["set"] == "after"
    assert (data["width"], data["fx"]) == (64, 60.0)
    seq = load_sequence(tmp_path / "seq" / "poses.json")
    for p, keys in (("p1", before), ("p2", after)):
        frames = seq[p]
        flags = [fr["key"] for fr in data["paths"][p]["frames"]]
        assert [f.image for f, k in zip(frames, flags) if k] == [c.image for c in keys]
        assert flags == ([True] + [False] * n) * (len(keys) - 1) + [True]
        # key poses are kept exactly
        for f, c in zip([f for f, k in zip(frames, flags) if k], keys):
            assert np.allclose(f.c2w, c.c2w)
        # no frame bridges the two paths: every frame centre lies within its own set's hull
        lo = np.min([c.center for c in keys], 0) - 1e-9
        hi = np.max([c.center for c in keys], 0) + 1e-9
        for f in frames:
            assert (f.center >= lo).all() and (f.center <= hi).all()
    t = {p: {f.time for f in fr} for p, fr in seq.items()}
    assert t == {"p1": {0}, "p2": {1}}
    # p1 starts at the first before image and ends at the last: nothing towards the after set
    assert seq["p1"][-1].image == "before/006.png" and seq["p2"][0].image == "after/000.png"
    assert all(f.image is None or not f.image.startswith("eval") for fr in seq.values()
               for f in fr)


def test_max_angle_picks_frames_per_gap(tmp_path):
    before = _orbit(4, "before", span=(0, 60))  # ~20 deg per gap
    after = _orbit(3, "after", span=(0, 10))  # ~5 deg per gap
    save_cameras(tmp_path / "cameras.json", before + after)
    build_sequence(tmp_path / "cameras.json", tmp_path / "poses.json",
                   InterpolateOptions(n=1, max_angle_deg=4.0, max_step=None))
    seq = load_sequence(tmp_path / "poses.json")
    for frames in seq.values():
        for a, b in zip(frames[:-1], frames[1:]):
            ang = np.degrees((Rotation.from_matrix(a.c2w[:3, :3]).inv()
                              * Rotation.from_matrix(b.c2w[:3, :3])).magnitude())
            assert ang <= 4.0 + 1e-6
    # the wide path got more frames per gap than the minimum n=1; the narrow one kept n=1
    assert len(seq["p1"]) > 4 + 3 * 1 and len(seq["p2"]) == 3 + 2 * 1


def test_default_frames_follow_the_path_not_the_photo_count(tmp_path):
    frames = {}
    for n in (10, 20, 40):  # the same 180 deg arc photographed 4x more densely
        save_cameras(tmp_path / f"c{n}.json", _orbit(n, "before", span=(0, 180))
                     + _orbit(n, "after", span=(0, 180), radius=2.4))
        s = build_sequence(tmp_path / f"c{n}.json", tmp_path / f"p{n}.json")
        frames[n] = s["p1"]["frames"]
        seq = load_sequence(tmp_path / f"p{n}.json")
        for a, b in zip(seq["p1"][:-1], seq["p1"][1:]):  # steps the tracker can follow
            ang = np.degrees((Rotation.from_matrix(a.c2w[:3, :3]).inv()
                              * Rotation.from_matrix(b.c2w[:3, :3])).magnitude())
            assert ang <= InterpolateOptions().max_angle_deg + 1e-6
    # sparse photos (20 deg apart): every gap filled to steps of at most max_angle_deg
    per_gap = int(np.ceil(20.0 / InterpolateOptions().max_angle_deg)) - 1
    assert per_gap >= 1 and frames[10] >= 10 + 9 * per_gap
    assert frames[40] < 1.4 * frames[10]  # 4x the photos, about the same frames


def test_reordering_fixes_shuffled_orbit(tmp_path, caplog):
    before = _orbit(12, "before", span=(0, 150))
    after = _orbit(6, "after", span=(10, 100), radius=2.4)
    perm = np.random.default_rng(4).permutation(12)
    shuffled = [before[i] for i in perm]
    save_cameras(tmp_path / "cameras.json", shuffled + after)
    with caplog.at_level(logging.INFO, logger="gdiff.interpolate"):
        summary = build_sequence(tmp_path / "cameras.json", tmp_path / "poses.json",
                                 InterpolateOptions(n=2, max_angle_deg=None, max_step=None))
    assert summary["p1"]["reordered"] and not summary["p2"]["reordered"]
    data = json.loads((tmp_path / "poses.json").read_text())
    order = data["paths"]["p1"]["order"]
    want = [c.image for c in before]
    assert order in (want, want[::-1])
    assert "largest step" in caplog.text and "has a jump" in caplog.text
    # with reordering off the capture order is kept
    build_sequence(tmp_path / "cameras.json", tmp_path / "p_never.json",
                   InterpolateOptions(n=2, reorder="never", max_angle_deg=None,
                                      max_step=None))
    kept = json.loads((tmp_path / "p_never.json").read_text())["paths"]["p1"]["order"]
    assert kept == [c.image for c in shuffled]


def test_short_path_on_random_points_beats_random_order():
    rng = np.random.default_rng(1)
    pts = rng.random((25, 2))
    cost = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    order = short_path(cost)
    assert sorted(order) == list(range(25))
    ln = sum(cost[a, b] for a, b in zip(order[:-1], order[1:]))
    rand = np.mean([sum(cost[a, b] for a, b in zip(p[:-1], p[1:]))
                    for p in (rng.permutation(25) for _ in range(20))])
    assert ln < 0.4 * rand


def test_step_costs_symmetric_zero_diagonal():
    cams = _orbit(5, "before")
    c = step_costs(cams, 2.0, 1.0)
    assert np.allclose(c, c.T) and np.allclose(np.diag(c), 0, atol=1e-6)


def test_errors_and_options(tmp_path):
    save_cameras(tmp_path / "cameras.json", _orbit(3, "before"))
    with pytest.raises(SceneError, match="no registered 'after' cameras"):
        build_sequence(tmp_path / "cameras.json", tmp_path / "poses.json")
    with pytest.raises(ConfigError, match="reorder"):
        from_config(InterpolateOptions, {"reorder": "sometimes"}, "interpolate")
    with pytest.raises(ConfigError, match="n must be"):
        from_config(InterpolateOptions, {"n": -1}, "interpolate")
