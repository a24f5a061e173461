"""Poses stage: COLMAP registration, known-pose import, failure modes, PLY, Sim3 scoring."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gdiff.align import orbit_radius, pose_errors, relative_rotation_errors, umeyama_sim3
from gdiff.cameras import cameras_to_json, cameras_to_transforms, load_cameras
from gdiff.errors import ConfigError, PosesError
from gdiff.io import write_image
from gdiff.options import from_config
from gdiff.sfm import (PosesOptions, discover_images, extraction_scale, proximity_pairs,
                       read_cameras_file, refine_model, run_poses, sequential_pairs,
                       set_from_path)
from gdiff.sfm.match import all_pairs, match_in_processes
from gdiff.sfm.colmap import _extract, _mapper_options, _read_descriptors, core_images
from gdiff.sfm.pairs import retrieval_pairs, word_histograms
from gdiff.splat.ply import read_points


def _linked_scene(src: Path, dst: Path) -> Path:
    """A scene folder whose image folders are symlinks into ``src`` (src stays untouched)."""
    dst.mkdir(parents=True)
    for name in ("before", "after", "eval"):
        (dst / name).symlink_to((src / name).resolve(), target_is_directory=True)
    return dst


def _noise_image(path: Path, seed: int, size=(96, 128)) -> None:
    rng = np.random.default_rng(seed)
    write_image(path, rng.random((*size, 3), dtype=np.float32))


@pytest.fixture(scope="module")
def gt_tiny(synth_tiny_dir):
    return read_cameras_file(Path(synth_tiny_dir) / "gt_cameras.json")


@pytest.fixture(scope="module")
def registered_tiny(synth_tiny_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("poses_tiny")
    summary = run_poses(synth_tiny_dir, out, PosesOptions(num_threads=2))
    return out, summary


# ------------------------------------------------------------------ COLMAP registration


def test_register_tiny_all_sets_accurate(registered_tiny, gt_tiny, synth_tiny_dir):
    out, summary = registered_tiny
    images = discover_images(synth_tiny_dir)
    assert summary["source"] == "colmap" and summary["matcher"] == "exhaustive"
    assert summary["registered"] == summary["images"]
    assert summary["mapper_attempts"] == 1  # all registered in the first run
    ref = summary["refinement"]
    assert ref["rounds"] == 3 and ref["reprojection_after"] <= ref["reprojection_before"]
    assert summary["images"] == {"before": 10, "after": 10, "eval_before": 3, "eval_after": 3}
    assert summary["mean_reprojection_error"] < 1.0
    cams = load_cameras(out / "cameras.json")
    # every image once, in input order, with its set and time
    assert [c.image for c in cams] == [n for n, _ in images]
    assert [c.set for c in cams] == [s for _, s in images]
    assert all(c.time == (0 if c.set in ("before", "eval_before") else 1) for c in cams)
    # one shared pinhole camera close to the true intrinsics
    g = gt_tiny[0]
    assert len({(c.fx, c.fy, c.cx, c.cy) for c in cams}) == 1
    assert abs(cams[0].fx - g.fx) / g.fx < 0.03 and abs(cams[0].fy - g.fy) / g.fy < 0.03
    # accuracy after Sim3 alignment (tiny is 128x96, so looser than the benchmark targets)
    err = pose_errors(cams, gt_tiny)
    assert len(err) == 26
    assert err.rot_err_deg.median() < 2.0
    assert err.center_err_frac.median() < 0.05
    for c in cams:
        assert np.allclose(c.c2w[:3, :3] @ c.c2w[:3, :3].T, np.eye(3), atol=1e-6)
        assert np.linalg.det(c.c2w[:3, :3]) > 0.99


def test_register_tiny_writes_model_and_points(registered_tiny):
    import pycolmap

    out, summary = registered_tiny
    xyz, rgb = read_points(out / "points.ply")
    assert xyz.shape[1] == 3 and rgb.shape == xyz.shape and 0 <= rgb.min() <= rgb.max() <= 1
    assert summary["num_points"] > 100
    assert len(xyz) == summary["num_points"] + summary["num_points_seeded"]
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    # the triangulated points first, then those seeded where none projects (not in the model)
    assert rec.num_reg_images() == 26 and rec.num_points3D() == summary["num_points"]
    xyz = xyz[:summary["num_points"]]
    # points are in front of the cameras that see them: project into cameras.json poses
    cams = load_cameras(out / "cameras.json")
    c = cams[0]
    p = (c.w2c[:3, :3] @ xyz.T.astype(np.float64)).T + c.w2c[:3, 3]
    front = p[:, 2] > 0
    uv = (c.K @ p[front].T).T
    uv = uv[:, :2] / uv[:, 2:]
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < c.width) & (uv[:, 1] >= 0) & (uv[:, 1] < c.height)
    assert inside.sum() > 50  # the first camera sees a good part of the cloud
    assert not list(out.glob(".poses_work_*"))  # temporary folder cleaned up


def _match_table(db: Path) -> dict[int, bytes]:
    import sqlite3

    con = sqlite3.connect(db)
    try:
        return {pid: data for pid, data in con.execute("SELECT pair_id, data FROM matches")}
    finally:
        con.close()


def test_matching_in_worker_processes_equals_one_matcher_thread(synth_tiny_dir, tmp_path):
    """The pairs dealt to two worker processes give exactly the matches one matcher thread gives
    for all of them (the same pairs, the same order of matches), merged into the database."""
    import pycolmap

    names = [f"{s}/{i:03d}.png" for s in ("before", "after") for i in range(4)]
    base = tmp_path / "base.db"
    _extract(base, Path(synth_tiny_dir), names, PosesOptions(num_threads=1), single_camera=True)
    one, split = tmp_path / "one.db", tmp_path / "split.db"
    for db in (one, split):
        shutil.copyfile(base, db)
    pairs = all_pairs(base)
    assert len(pairs) == 28 and set(map(frozenset, pairs)) == {
        frozenset((a, b)) for i, a in enumerate(names) for b in names[i + 1:]}
    mo = pycolmap.FeatureMatchingOptions()
    mo.num_threads = 1
    mo.skip_geometric_verification = True
    po = pycolmap.ImportedPairingOptions()
    (tmp_path / "pairs.txt").write_text("".join(f"{a} {b}\n" for a, b in pairs))
    po.match_list_path = str(tmp_path / "pairs.txt")
    pycolmap.match_image_pairs(one, matching_options=mo, pairing_options=po,
                               device=pycolmap.Device.cpu)
    work = tmp_path / "work"
    work.mkdir()
    assert match_in_processes(split, work, pairs, num_threads=2) == 2
    expected, got = _match_table(one), _match_table(split)
    assert len(expected) == 28 and sum(bool(d) for d in expected.values()) >= 8
    assert got == expected
    assert not list(work.glob("*.db"))  # the workers' copies are gone


def test_a_failing_matching_worker_is_a_poses_error(tmp_path):
    db = tmp_path / "broken.db"
    db.write_bytes(b"this is no database")
    with pytest.raises(PosesError, match="matching failed in a worker process"):
        match_in_processes(db, tmp_path, [("a.png", "b.png")], num_threads=1)


def test_refine_model_recovers_focal_and_removes_outliers(registered_tiny, gt_tiny):
    """The final refinement pulls a 4 % focal-length error back and drops gross outliers."""
    import pycolmap

    out, _ = registered_tiny
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    cam = next(iter(rec.cameras.values()))
    true_f = gt_tiny[0].fx
    p = np.asarray(cam.params, dtype=np.float64)
    p[:2] *= 0.96
    cam.params = p.tolist()
    # corrupt 40 observations by 8 px (false matches the mapper kept)
    rng = np.random.default_rng(0)
    corrupted = 0
    for iid in rec.reg_image_ids():
        im = rec.images[iid]
        obs = [k for k, pt in enumerate(im.points2D) if pt.has_point3D()]
        for k in rng.choice(obs, size=5, replace=False):
            im.points2D[int(k)].xy = im.points2D[int(k)].xy + rng.choice([-8.0, 8.0], size=2)
            corrupted += 1
        if corrupted >= 40:
            break
    n_obs = sum(len(rec.points3D[i].track.elements) for i in rec.points3D)
    rep = refine_model(rec, max_error=2.0, iterations=3, num_threads=2)
    f = np.asarray(rec.cameras[cam.camera_id].params)[:2]
    assert np.all(np.abs(f - true_f) / true_f < 0.02), (f, true_f)
    assert corrupted <= rep["removed_observations"] < 0.2 * n_obs
    assert rep["reprojection_after"] < 0.6 < rep["reprojection_before"]
    # nothing left beyond the threshold
    for pid in rec.points3D:
        assert rec.points3D[pid].error <= 2.0 + 1e-6
    # zero rounds leave the model untouched
    before = np.asarray(rec.cameras[cam.camera_id].params).copy()
    assert refine_model(rec, 2.0, 0)["removed_observations"] == 0
    assert np.array_equal(np.asarray(rec.cameras[cam.camera_id].params), before)


def test_domain_size_pooling_changes_descriptors(synth_tiny_dir, tmp_path):
    import pycolmap

    names = [f"before/{i:03d}.png" for i in range(3)]
    desc = {}
    for dsp in (False, True):
        db = tmp_path / f"dsp{dsp}.db"
        _extract(db, Path(synth_tiny_dir), names,
                 PosesOptions(domain_size_pooling=dsp, num_threads=1), single_camera=True)
        d = pycolmap.Database.open(str(db))
        try:
            img = d.read_all_images()[0]
            desc[dsp] = (np.asarray(d.read_keypoints(img.image_id))[:, :2],
                         np.asarray(d.read_descriptors(img.image_id).data))
        finally:
            d.close()
    (k0, d0), (k1, d1) = desc[False], desc[True]
    assert len(k0) > 50 and len(k1) > 50
    assert 0.5 < len(k1) / len(k0) < 2.0  # a similar number of features
    # at the same keypoint location the pooled descriptor differs from the plain one
    dist = np.linalg.norm(k0[:, None] - k1[None], axis=2)
    i, j = np.unravel_index(np.argmin(dist), dist.shape)
    assert dist[i, j] < 0.1 and not np.array_equal(d0[i], d1[j])


def test_thresholds_scale_with_extraction_size():
    assert extraction_scale({"a": (320, 240), "b": (320, 240)}, 1600) == 1.0
    assert extraction_scale({"a": (4000, 3000), "b": (320, 240)}, 1600) == 2.5
    assert extraction_scale({"a": (4000, 3000)}, -1) == 1.0  # -1: no downscaling
    opts = PosesOptions(max_reproj_error=2.0)
    mp = _mapper_options(opts, 40, pixel_scale=2.5)
    assert mp.mapper.filter_max_reproj_error == pytest.approx(5.0)
    assert mp.triangulation.complete_max_reproj_error == pytest.approx(5.0)
    assert mp.mapper.abs_pose_max_error == pytest.approx(15.0)
    relaxed = _mapper_options(opts, 40, pixel_scale=1.0, seed=7, relax=2.0)
    assert relaxed.mapper.filter_max_reproj_error == pytest.approx(4.0)
    assert relaxed.random_seed == 7


# ------------------------------------------------------------------ known poses


def test_known_poses_from_cameras_json(synth_tiny_dir, gt_tiny, tmp_path):
    scene = _linked_scene(Path(synth_tiny_dir), tmp_path / "scene")
    # the ground-truth layout (intrinsics block, 'file' per frame) is accepted as cameras.json
    (scene / "cameras.json").write_text((Path(synth_tiny_dir) / "gt_cameras.json").read_text())
    out = tmp_path / "poses"
    summary = run_poses(scene, out, PosesOptions(num_threads=2, refine_known=False))
    assert summary["source"] == "known"
    assert summary["registered"] == summary["images"]
    cams = load_cameras(out / "cameras.json")
    gt = {c.image: c for c in gt_tiny}
    for c in cams:
        assert np.allclose(c.c2w, gt[c.image].c2w, atol=1e-9)
        assert (c.fx, c.cx) == (gt[c.image].fx, gt[c.image].cx)
    # refined by default: exact poses stay where they are (in their own frame, no alignment)
    refined = run_poses(scene, tmp_path / "refined", PosesOptions(num_threads=2))
    assert refined["refined_images"] == len(cams)
    assert refined["turned_to_partner"] == refined["turned_in_common"] == []
    again = load_cameras(tmp_path / "refined" / "cameras.json")
    # within the precision bundle adjustment reaches on 128 px photos (about half a pixel)
    assert np.median(relative_rotation_errors(again, gt_tiny)) < 0.3
    assert pose_errors(again, gt_tiny)["center_err_frac"].median() < 0.01
    assert all((c.fx, c.cx) == (gt[c.image].fx, gt[c.image].cx) for c in again)
    xyz, _ = read_points(out / "points.ply")
    assert summary["num_points"] > 100
    assert len(xyz) == summary["num_points"] + summary["num_points_seeded"]
    xyz = xyz[:summary["num_points"]]  # the triangulated ones (then the seeded)
    assert summary["mean_reprojection_error"] < 1.0
    # triangulated with the true poses, points lie in the synth room (|x|,|y| < 3.2, 0<=z<=2.8)
    inside = (np.abs(xyz[:, :2]) < 3.3).all(1) & (xyz[:, 2] > -0.1) & (xyz[:, 2] < 2.9)
    assert inside.mean() > 0.95


def test_known_poses_from_transforms_json(synth_tiny_dir, gt_tiny, tmp_path):
    scene = _linked_scene(Path(synth_tiny_dir), tmp_path / "scene")
    subset = [c for c in gt_tiny if c.set in ("before", "after")]
    data = cameras_to_transforms(subset)
    for fr in data["frames"]:
        fr["file_path"] = "./" + fr["file_path"]
    (scene / "transforms.json").write_text(json.dumps(data))
    images = [(c.image, c.set) for c in subset]
    out = tmp_path / "poses"
    summary = run_poses(scene, out, PosesOptions(source="known", num_threads=2,
                                                 refine_known=False), images=images)
    assert summary["source"] == "known" and summary["num_points"] > 50
    cams = load_cameras(out / "cameras.json")
    assert [c.image for c in cams] == [c.image for c in subset]
    for c, g in zip(cams, subset):
        # OpenGL axes in transforms.json came back as OpenCV c2w
        assert np.allclose(c.c2w, g.c2w, atol=1e-9)


def test_known_source_without_file_is_an_error(synth_tiny_dir, tmp_path):
    scene = _linked_scene(Path(synth_tiny_dir), tmp_path / "scene")
    with pytest.raises(PosesError, match="cameras.json or transforms.json"):
        run_poses(scene, tmp_path / "poses", PosesOptions(source="known"))


def test_known_poses_missing_for_too_many_images(synth_tiny_dir, gt_tiny, tmp_path):
    scene = _linked_scene(Path(synth_tiny_dir), tmp_path / "scene")
    keep = [c for c in gt_tiny if c.image not in ("after/000.png", "after/001.png",
                                                   "after/002.png")]
    (scene / "cameras.json").write_text(json.dumps(cameras_to_json(keep)))
    with pytest.raises(PosesError, match="after: 3 of 10") as e:
        run_poses(scene, tmp_path / "poses", PosesOptions())
    assert "after/001.png" in str(e.value)
    assert not (tmp_path / "poses" / "cameras.json").exists()


# ------------------------------------------------------------------ failures


def test_unregistered_fraction_error_and_drop(synth_tiny_dir, tmp_path, caplog):
    scene = _linked_scene(Path(synth_tiny_dir), tmp_path / "scene")
    # a set of real images plus pure-noise photos that cannot be registered
    (scene / "before").unlink()
    (scene / "before").mkdir()
    for p in sorted((Path(synth_tiny_dir) / "before").glob("*.png")):
        (scene / "before" / p.name).symlink_to(p.resolve())
    for k in range(3):
        _noise_image(scene / "before" / f"90{k}.png", k)
    images = [(f"before/{p.name}", "before") for p in sorted((scene / "before").glob("*.png"))]
    images += [(f"after/{i:03d}.png", "after") for i in range(10)]
    noise = ["before/900.png", "before/901.png", "before/902.png"]
    # 3 of 13 before images lost = 23% > 20%
    with pytest.raises(PosesError, match=r"before: 3 of 13 \(" + ", ".join(noise) + r"\)"):
        run_poses(scene, tmp_path / "p1", PosesOptions(num_threads=2, mapper_attempts=1),
                  images=images)
    # with a looser limit the noise images are dropped with a warning (sequential matcher)
    with caplog.at_level(logging.WARNING, logger="gdiff.sfm"):
        summary = run_poses(scene, tmp_path / "p2",
                            PosesOptions(max_unregistered_fraction=0.3, matcher="sequential",
                                         sequential_overlap=3, sequential_links=3,
                                         num_threads=2), images=images)
    assert summary["matcher"] == "sequential"
    assert summary["dropped"] == noise
    # the noise images stay out however often mapping is retried (seeds, looser thresholds)
    assert summary["mapper_attempts"] == 3
    assert summary["registered"] == {"before": 10, "after": 10}
    assert "dropping 3 image(s)" in caplog.text
    names = [c.image for c in load_cameras(tmp_path / "p2" / "cameras.json")]
    assert names == [n for n, _ in images if "90" not in n]


def test_unmatchable_images_raise_poses_error(tmp_path):
    scene = tmp_path / "noise"
    for st in ("before", "after"):
        for i in range(3):
            _noise_image(scene / st / f"{i:03d}.png", hash((st, i)) % 1000)
    with pytest.raises(PosesError, match="could not register") as e:
        run_poses(scene, tmp_path / "poses", PosesOptions(num_threads=2))
    msg = str(e.value)
    assert "overlap" in msg and "known poses" in msg
    assert not (tmp_path / "poses" / "cameras.json").exists()
    assert not list((tmp_path / "poses").glob(".poses_work_*"))


# ------------------------------------------------------------------ helpers


def test_options_validation():
    assert from_config(PosesOptions, {"matcher": "sequential"}, "poses").matcher == "sequential"
    with pytest.raises(ConfigError, match="poses"):
        from_config(PosesOptions, {"source": "gps"}, "poses")
    with pytest.raises(ConfigError, match="camera_model"):
        from_config(PosesOptions, {"camera_model": "FISHEYE"}, "poses")
    assert from_config(PosesOptions, {"camera_model": "OPENCV"}, "poses").camera_model == "OPENCV"
    with pytest.raises(ConfigError, match="min_points_per_image"):
        from_config(PosesOptions, {"min_points_per_image": -1}, "poses")
    with pytest.raises(ConfigError, match="unknown key"):
        from_config(PosesOptions, {"matchr": "x"}, "poses")
    with pytest.raises(ConfigError, match="max_reproj_error"):
        from_config(PosesOptions, {"max_reproj_error": 0}, "poses")
    with pytest.raises(ConfigError, match="mapper_attempts"):
        from_config(PosesOptions, {"mapper_attempts": 0}, "poses")


def test_set_from_path():
    assert set_from_path("before/a.png") == "before"
    assert set_from_path("after/x/a.png") == "after"
    assert set_from_path("eval/before/000.png") == "eval_before"
    assert set_from_path("eval/after/000.png") == "eval_after"
    assert set_from_path("eval/masks/000.png") is None
    assert set_from_path("a.png") is None


def test_sequential_pairs_cover_neighbours_and_link_sets():
    a = [f"before/{i:03d}" for i in range(20)]
    b = [f"after/{i:03d}" for i in range(20)]
    pairs = set(sequential_pairs([a, b], overlap=3, links=2))
    for g in (a, b):
        for i in range(20):
            for k in (1, 2, 3):
                x, y = g[i], g[(i + k) % 20]
                assert (min(x, y), max(x, y)) in pairs
    cross = [p for p in pairs if p[0].startswith("after") != p[1].startswith("after")]
    linked = {x for p in cross for x in p}
    assert linked == set(a) | set(b)  # every image has links into the other set
    assert len(pairs) < 40 * 39 // 2 / 2  # far fewer than exhaustive
    assert all(x < y for x, y in pairs)


def test_word_histograms_rank_images_of_one_place_first():
    # three places, each with its own mix of 40 descriptor prototypes; images of a place draw
    # noisy copies of them and share a background of generic descriptors
    rng = np.random.default_rng(0)
    protos = [rng.integers(0, 256, (40, 128)) for _ in range(3)]
    generic = rng.integers(0, 256, (30, 128))
    descs, place = [], []
    for p in range(3):
        for _ in range(5):
            pick = np.concatenate([protos[p][rng.integers(0, 40, 150)],
                                   generic[rng.integers(0, 30, 100)]])
            descs.append(np.clip(pick + rng.normal(0, 12, pick.shape), 0, 255).astype(np.uint8))
            place.append(p)
    v = word_histograms(descs, num_words=64, seed=0)
    assert v.shape == (15, 64) and np.allclose(np.linalg.norm(v, axis=1), 1.0, atol=1e-5)
    names = [f"before/{i:03d}.png" for i in range(15)]
    pairs = retrieval_pairs([names], dict(zip(names, v)), neighbours=4, overlap=0)
    assert len(pairs) <= 15 * 4
    same = sum(place[names.index(a)] == place[names.index(b)] for a, b in pairs)
    assert same == len(pairs)  # 4 neighbours = the other images of its place
    # capture-order neighbours are added on top
    with_order = retrieval_pairs([names], dict(zip(names, v)), neighbours=4, overlap=1)
    assert ("before/004.png", "before/005.png") in with_order


def test_retrieval_pairs_give_every_image_partners_in_every_set():
    # two visits of one place under different light: every image resembles the images of its
    # own visit more than any of the other, so a ranking over all images would pair visits
    # only with themselves
    rng = np.random.default_rng(1)
    place = rng.normal(size=(6, 16))
    light = rng.normal(size=(2, 16)) * 3.0
    before = [f"before/{i:03d}.png" for i in range(6)]
    after = [f"after/{i:03d}.png" for i in range(6)]
    vec = {}
    for names, lt in ((before, light[0]), (after, light[1])):
        for i, n in enumerate(names):
            v = place[i] + lt + rng.normal(size=16) * 0.1
            vec[n] = v / np.linalg.norm(v)
    # the visit dominates the similarity: an image's 4 nearest over all images are its own visit's
    names = before + after
    sim = np.stack([vec[n] for n in names]) @ np.stack([vec[n] for n in names]).T
    np.fill_diagonal(sim, -np.inf)
    assert all(j // 6 == i // 6 for i in range(12) for j in np.argsort(-sim[i])[:4])
    pairs = retrieval_pairs([before, after], vec, neighbours=4, overlap=0)
    cross = {(a, b) for a, b in pairs if a.split("/")[0] != b.split("/")[0]}
    # 2 per set: each image has partners in the other visit, the most similar first
    for i in range(6):
        assert ("after/%03d.png" % i, "before/%03d.png" % i) in cross
    assert all(any(n in p for p in cross) for n in names)
    assert len(pairs) <= 12 * 4


def test_core_images_spread_over_every_set():
    images = [(f"b{i:02d}", "before") for i in range(40)] + \
        [(f"a{i:02d}", "after") for i in range(40)] + [("e0", "eval_before"), ("e1", "eval_after")]
    assert core_images(images, None) == [n for n, _ in images]
    assert core_images(images, 82) == [n for n, _ in images]
    core = core_images(images, 20)
    b = [n for n in core if n.startswith("b")]
    a = [n for n in core if n.startswith("a")]
    assert len(b) == len(a) == 10 and {"e0", "e1"} <= set(core)  # small sets are kept
    assert b[0] == "b00" and b[-1] == "b39"  # the whole capture path
    steps = np.diff([int(n[1:]) for n in b])
    assert steps.min() >= 4 and steps.max() <= 5
    assert core == [n for n, _ in images if n in set(core)]  # input order


def test_images_beyond_the_mapped_core_are_registered_to_it(synth_tiny_dir, gt_tiny,
                                                            tmp_path):
    # 18 of the 26 images are mapped, the other 8 registered one by one to that model
    summary = run_poses(synth_tiny_dir, tmp_path / "p",
                        PosesOptions(map_max_images=18, num_threads=2))
    assert summary["mapped_images"] == 18
    assert summary["registered"] == summary["images"]
    cams = load_cameras(tmp_path / "p" / "cameras.json")
    err = pose_errors(cams, gt_tiny)
    assert len(err) == 26
    assert err.rot_err_deg.median() < 2.0 and err.center_err_frac.median() < 0.05
    core = set(core_images(discover_images(synth_tiny_dir), 18))
    rest = err[~err["image"].isin(core)]
    assert len(rest) == 8 and rest.rot_err_deg.max() < 5.0


def test_retrieval_matching_on_real_features(synth_tiny_dir, gt_tiny, tmp_path):
    # visual-word similarity of real SIFT features ranks nearby views of the orbit first
    cams = [c for c in gt_tiny if c.set == "before"]
    names = [c.image for c in cams]
    _extract(tmp_path / "db.db", Path(synth_tiny_dir), names, PosesOptions(), True)
    v = word_histograms(_read_descriptors(tmp_path / "db.db", names), seed=0)
    sim = v @ v.T
    ang = np.array([[np.degrees(np.arccos(np.clip(a.c2w[:3, 2] @ b.c2w[:3, 2], -1, 1)))
                     for b in cams] for a in cams])
    np.fill_diagonal(sim, -1)
    best = sim.argmax(axis=1)
    assert np.median(ang[np.arange(len(cams)), best]) < np.median(ang[ang > 0])
    # and registration from retrieval pairs alone holds every image
    summary = run_poses(synth_tiny_dir, tmp_path / "p",
                        PosesOptions(matcher="retrieval", retrieval_neighbours=4,
                                     sequential_overlap=1, num_threads=2))
    assert summary["matcher"] == "retrieval"
    assert summary["registered"] == summary["images"]
    n = sum(summary["images"].values())
    assert PosesOptions(exhaustive_max_images=None).exhaustive_limit() == 2 * (20 + 8) + 1
    assert PosesOptions(exhaustive_max_images=5).exhaustive_limit() == 5
    assert n * (n - 1) // 2 > n * 5  # fewer pairs than exhaustive were matched


def test_proximity_pairs_prefers_nearby_facing_cameras(gt_tiny):
    cams = [c for c in gt_tiny if c.set == "before"]
    pairs = proximity_pairs(cams, k=2)
    # on an orbit, nearest neighbours are the capture-order neighbours
    for i in range(1, len(cams) - 1):
        assert (cams[i - 1].image, cams[i].image) in pairs


def test_umeyama_recovers_similarity():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(30, 3))
    R = Rotation.from_rotvec([0.3, -1.2, 0.7]).as_matrix()
    dst = 2.5 * src @ R.T + np.array([1.0, -2.0, 0.5])
    s, R2, t = umeyama_sim3(src, dst)
    assert s == pytest.approx(2.5) and np.allclose(R2, R) and np.allclose(t, [1, -2, 0.5])
    # a reflection is never returned
    s, R3, _ = umeyama_sim3(src, src * np.array([1, 1, -1]))
    assert np.linalg.det(R3) == pytest.approx(1.0)


def test_pose_errors_zero_for_transformed_copy_and_detect_error(gt_tiny):
    R = Rotation.from_rotvec([0.1, 0.4, -0.2]).as_matrix()
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = 0.5 * R, [3.0, 1.0, -1.0]
    est = []
    for c in gt_tiny:
        c2w = T @ c.c2w
        c2w[:3, :3] /= 0.5  # keep the rotation orthonormal
        est.append(c.with_pose(c2w))
    df = pose_errors(est, gt_tiny)
    assert df.rot_err_deg.max() < 1e-5 and df.center_err_frac.max() < 1e-9
    assert df.attrs["scale"] == pytest.approx(2.0)
    # perturb one camera by 5 degrees, shift another by 10% of the orbit radius
    radius = orbit_radius(np.stack([c.center for c in gt_tiny]))
    bad = est[4].c2w.copy()
    bad[:3, :3] = Rotation.from_rotvec([0, 0, np.radians(5)]).as_matrix() @ bad[:3, :3]
    est[4] = est[4].with_pose(bad)
    moved = est[7].c2w.copy()
    moved[:3, 3] += np.array([0.0, 0.0, 0.1 * radius]) / 2.0  # est frame is scaled by 1/2
    est[7] = est[7].with_pose(moved)
    df = pose_errors(est, gt_tiny)
    assert df.rot_err_deg.iloc[4] == pytest.approx(5.0, abs=0.05)
    assert 0.08 < df.center_err_frac.iloc[7] < 0.11
    assert df.center_err_frac.drop(7).median() < 0.01


def test_two_runs_on_the_same_photos_give_identical_poses(synth_tiny_dir, tmp_path):
    """With ``repeatable`` (default) runs write byte-identical cameras and points, whether
    matching runs on one thread or several: the fit starts from the same model every time (with
    ``repeatable: false`` these runs differed)."""
    outs = []
    for k in range(3):
        out = tmp_path / f"run{k}"
        run_poses(synth_tiny_dir, out, PosesOptions(num_threads=1 if k == 0 else 2))
        outs.append(out)
    for out in outs[1:]:
        for name in ("cameras.json", "points.ply"):
            assert (out / name).read_bytes() == (outs[0] / name).read_bytes(), name
