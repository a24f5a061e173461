"""The bench table (gdiff.bench) from a made-up results folder."""

import json
import math

import numpy as np
import pandas as pd
import pytest

from gdiff import bench as Bn
from gdiff.io import write_csv

BENCH_HEADER = "s\th:m:s\tmax_rss\tmax_vms\tmax_uss\tmax_pss\tio_in\tio_out\tmean_load\tcpu_time\n"


def _scene(results, name, tps, rules, psnr=(20.0, 22.0)):
    """results/<name>/: eval/metrics.csv (one view per (TP, FN) of method m; FP 0; objects:
    found when TP >= FN), benchmarks/<rule>.tsv (wall, pss, cpu), fit/quality.csv."""
    rows = [{"scene": name, "view": f"{i:03d}", "method": "m", "TP": tp, "FP": 0, "FN": fn,
             "obj_N": 1, "obj_found": int(tp >= fn)} for i, (tp, fn) in enumerate(tps)]
    write_csv(results / name / "eval" / "metrics.csv", pd.DataFrame(rows))
    for rule, (wall, pss, cpu) in rules.items():
        p = results / name / "benchmarks" / f"{rule}.tsv"
        p.parent.mkdir(parents=True, exist_ok=True)
        # RSS summed over a rule's processes (2 x: a forked worker) above the PSS, which counts
        # the pages they share once: the table reports the PSS
        p.write_text(BENCH_HEADER + f"{wall}\t0:00:01\t{2 * pss}\t1\t1\t{pss}\t0\t0\t0\t{cpu}\n")
    write_csv(results / name / "fit" / "quality.csv", pd.DataFrame(
        [{"image": "a.png", "set": "before", "time": 0.0, "psnr": psnr[0], "ssim": 0.9},
         {"image": "b.png", "set": "after", "time": 1.0, "psnr": psnr[1], "ssim": 0.9}]))


def test_bench_table_pooled_costs_and_seed_means(tmp_path):
    res = tmp_path / "results"
    # two seeds of a preset and one real scene (named like a seed, but not a preset given)
    _scene(res, "demo_s0", [(30, 10), (10, 30)], {"fit": (100, 900, 180), "poses": (10, 300, 8)})
    _scene(res, "demo_s1", [(20, 20)], {"fit": (300, 1100, 500), "poses": (30, 500, 12)},
           psnr=(24.0, 26.0))
    _scene(res, "desk_s1", [(5, 5)], {"fit": (50, 700, 90)})
    (res / "desk_s1" / "eval" / "fit_quality.csv").write_text(
        "view,time,psnr\n000,0,17\n001,0,19\n000,1,19\n")
    (res / "plots").mkdir()  # not a scene
    assert Bn.scene_folders(res) == ["demo_s0", "demo_s1", "desk_s1"]
    t = Bn.read_results(res, presets=["demo"]).set_index("scene")
    assert list(t.index) == ["demo_s0", "demo_s1", "desk_s1", "demo (mean of 2)"]
    s0 = t.loc["demo_s0"]
    assert s0["R"] == pytest.approx(40 / 80) and s0["P"] == 1.0 and s0["obj_R"] == 0.5
    assert s0["n_views"] == 2 and math.isnan(s0["box_R"])
    assert s0["wall_fit"] == 100 and s0["cpu_poses"] == 8 and s0["mb_fit"] == 900
    assert (s0["wall_s"], s0["cpu_s"], s0["peak_mb"]) == (110, 188, 900)
    assert (s0["psnr_t0"], s0["psnr_t1"], s0["psnr_views"]) == (20.0, 22.0, "train")
    assert s0["disk_mb"] > 0
    # the real scene's PSNR is over its eval views (evaluate's fit_quality.csv); no poses timing
    d = t.loc["desk_s1"]
    assert (d["psnr_t0"], d["psnr_t1"], d["psnr_views"]) == (18.0, 19.0, "eval")
    assert math.isnan(d["wall_poses"]) and d["wall_s"] == 50
    # seed means: every number averaged over the two seeds
    mean = t.loc["demo (mean of 2)"]
    assert mean["R"] == pytest.approx((0.5 + 0.5) / 2) and mean["obj_R"] == pytest.approx(0.75)
    assert mean["wall_s"] == pytest.approx((110 + 330) / 2)
    assert mean["psnr_t0"] == pytest.approx(22.0) and mean["peak_mb"] == pytest.approx(1000)
    # text and markdown: one line per scene x method, rules in run order
    text = Bn.format_table(t.reset_index())
    head = text.splitlines()[0]
    assert head.index("poses s/cpu/MB") < head.index("fit s/cpu/MB")
    assert "box_R" not in head  # no scene has boxes
    assert len(text.splitlines()) == 2 + 4
    md = Bn.format_table(t.reset_index(), markdown=True)
    assert md.splitlines()[2].startswith("| demo_s0 | m | 2 | 1.000 | 0.500 |")
    assert "| 100/180/900 |" in md.splitlines()[2]
    # a scene without metrics yet still gets a row with its costs
    (res / "demo_s1" / "eval" / "metrics.csv").unlink()
    t2 = Bn.read_results(res, ["demo_s1"], presets=[]).set_index("scene")
    assert t2.loc["demo_s1", "method"] == "" and t2.loc["demo_s1", "wall_fit"] == 300


def test_synth_groups_only_named_presets():
    names = ["demo_s2", "demo_s0", "desk_s1", "lightchange_s0", "demo"]
    assert Bn.synth_groups(names, ["demo", "lightchange"]) == {
        "demo": ["demo_s0", "demo_s2"], "lightchange": ["lightchange_s0"]}
    assert Bn.synth_groups(names, []) == {}


def test_scaling_table_growth_per_step_and_quality(tmp_path):
    res = tmp_path / "results"
    # poses grows x3 from 10 to 20 photos (more than linear), the fit stays flat; the 40-photo
    # scene has no partition run yet
    _scene(res, "demo_p10", [(30, 10)], {"poses": (10, 300, 8), "fit": (100, 900, 180)})
    _scene(res, "demo_p20", [(20, 20)], {"poses": (30, 300, 8), "fit": (110, 900, 180)},
           psnr=(24.0, 26.0))
    _scene(res, "demo_p40", [(10, 30)], {"poses": (45, 300, 8)})
    photos = {"demo_p40": 40, "demo_p10": 10, "demo_p20": 20}
    sc = Bn.scaling_table(Bn.read_results(res, list(photos)), photos, method="m").set_index("row")
    assert list(sc.columns) == ["10 s", "20 s", "40 s", "x 10->20", "x 20->40"]
    assert sc.attrs["photo_ratio"] == {"x 10->20": 2.0, "x 20->40": 2.0}
    assert sc.loc["poses", "x 10->20"] == pytest.approx(3.0)
    assert sc.loc["poses", "x 20->40"] == pytest.approx(1.5)
    assert sc.loc["fit", "x 10->20"] == pytest.approx(1.1)
    assert math.isnan(sc.loc["fit", "40 s"]) and math.isnan(sc.loc["fit", "x 20->40"])
    assert sc.loc["total", "10 s"] == pytest.approx(110) and sc.loc["total", "40 s"] == 45
    assert sc.loc["F1 (m)", "10 s"] == pytest.approx(2 * 30 / (2 * 30 + 10))
    assert sc.loc["PSNR t1", "20 s"] == pytest.approx(26.0)
    text = Bn.format_scaling(sc.reset_index())
    assert "| poses | 10.0 | 30.0 | 45.0 | 3.00 | 1.50 |" in text
    assert "x 10->20 (photos x2.00)" in text and "10+10 photos: s" in text


def test_fit_seed_runs_sheet_and_means(tmp_path):
    """--fit-seeds: every scene of the sheet once per fit seed (``fit.seed`` set, other
    overrides kept), and the table's mean row per scene over its runs; preset means cover the
    runs of every seed."""
    from gdiff.scene import discover_scenes

    rows = Bn.with_fit_seeds([{"name": "demo_s0", "path": "synth:demo:0"},
                              {"name": "desk", "path": "synth:tiny", "fit.max_side": 64}], [0, 2])
    assert [r["name"] for r in rows] == ["demo_s0_f0", "demo_s0_f2", "desk_f0", "desk_f2"]
    sheet = tmp_path / "scenes.tsv"
    pd.DataFrame(rows, dtype=object).fillna("").to_csv(sheet, sep="\t", index=False)
    specs = discover_scenes(str(sheet))
    assert specs["demo_s0_f2"].overrides == {"fit": {"seed": 2}}
    assert specs["demo_s0_f2"].synth_preset == "demo" and specs["demo_s0_f2"].synth_seed == 0
    assert specs["desk_f0"].overrides == {"fit": {"max_side": 64, "seed": 0}}
    assert isinstance(specs["desk_f0"].overrides["fit"]["max_side"], int)
    assert Bn.with_fit_seeds(rows[:1], []) == rows[:1]

    res = tmp_path / "results"
    _scene(res, "demo_s0_f0", [(30, 10)], {"fit": (100, 900, 180)}, psnr=(20.0, 22.0))
    _scene(res, "demo_s0_f2", [(10, 30)], {"fit": (120, 900, 180)}, psnr=(22.0, 24.0))
    _scene(res, "desk_f1", [(20, 20)], {"fit": (50, 700, 90)})  # a folder named like a run
    assert Bn.fit_seed_groups(Bn.scene_folders(res), [0, 2]) == {
        "demo_s0": ["demo_s0_f0", "demo_s0_f2"]}
    t = Bn.read_results(res, presets=["demo"], fit_seeds=[0, 2]).set_index("scene")
    assert list(t.index) == ["demo_s0_f0", "demo_s0_f2", "desk_f1",
                             "demo_s0 (mean of 2 fit seeds)", "demo (mean of 2)"]
    mean = t.loc["demo_s0 (mean of 2 fit seeds)"]
    assert mean["R"] == pytest.approx(0.5) and mean["psnr_t0"] == pytest.approx(21.0)
    assert mean["wall_fit"] == pytest.approx(110)
    assert t.loc["demo (mean of 2)", "R"] == pytest.approx(0.5)


def test_compare_objects_puts_each_judged_object_on_the_scenes_objects(synth_tiny_dir, tmp_path):
    """The compare stage's kept IDs and dropped candidates, placed by their world positions in
    the registered frame (a similarity away from the scene's own), land on the scene's objects:
    the removed one found, the added one dropped, a static one kept by mistake, one on no
    object at all."""
    from gdiff.bench import (compare_object_counts, compare_objects, format_compare_objects,
                             read_compare_objects)
    from gdiff.cameras import cameras_to_json
    from gdiff.sfm import read_cameras_file

    meta = json.loads((synth_tiny_dir / "meta.json").read_text())
    box = {o["name"]: {st: np.asarray(o[st]["bbox_world"]) for st in ("before", "after")
                       if o[st]["present"]} for o in meta["objects"]}
    changed = {o["name"]: o["changed"] for o in meta["objects"]}
    removed = next(n for n, b in box.items() if changed[n] and "after" not in b)
    added = next(n for n, b in box.items() if changed[n] and "before" not in b)
    static = next(n for n in box if not changed[n])
    s, c, sn = 2.5, np.cos(0.7), np.sin(0.7)
    R, t = np.array([[c, -sn, 0], [sn, c, 0], [0, 0, 1]]), np.array([1.0, -2.0, 0.5])

    def to_registered(x):  # x_gt = s R x_reg + t
        return R.T @ (np.asarray(x) - t) / s

    cams = read_cameras_file(synth_tiny_dir / "gt_cameras.json")
    for cam in cams:
        c2w = cam.c2w.copy()
        c2w[:3, :3] = R.T @ c2w[:3, :3]
        c2w[:3, 3] = to_registered(c2w[:3, 3])
        cam.c2w = c2w
    res = tmp_path / "results" / "tiny"
    (res / "poses").mkdir(parents=True)
    (res / "poses" / "cameras.json").write_text(json.dumps(cameras_to_json(cams)))
    (res / "input").mkdir()
    (res / "input" / "manifest.json").write_text(json.dumps({"scene": str(synth_tiny_dir)}))
    rows = []
    for inst, (name, state, types, verdict) in enumerate(
            [(removed, "before", "removed", "kept: 3D"), (added, "after", "added", "dropped"),
             (static, "before", "removed", "kept: colour")], start=1):
        x, y, z = to_registered(box[name][state].mean(0))
        rows.append(dict(instance=inst, ids=str(inst), types=types, n_t0=3, n_t1=0,
                         n_confirmed=3, area=100.0, x=x, y=y, z=z, size=0.1, support=0.1 * inst,
                         colour=0.3, verdict=verdict))
    x, y, z = to_registered([50.0, 50.0, 50.0])  # far from every object
    rows.append(dict(rows[0], instance=9, ids="9", x=x, y=y, z=z))
    (res / "change").mkdir()
    pd.DataFrame(rows).to_csv(res / "change" / "candidates.csv", index=False)
    kept = pd.DataFrame([dict(id=r["instance"], type=r["types"], **{k: r[k] for k in (
        "n_t0", "n_t1", "area", "instance", "x", "y", "z", "size", "support", "colour")})
        for r in rows if r["verdict"] != "dropped"])
    kept.to_csv(res / "change" / "changes.csv", index=False)
    objects = compare_objects(res).set_index("object")
    assert objects.loc[removed, "verdict"] == "kept" and objects.loc[removed, "instances"] == "1"
    assert objects.loc[added, "verdict"] == "dropped"
    assert objects.loc[added, "support"] == pytest.approx(0.2)
    assert not objects.loc[static, "changed"] and objects.loc[static, "instances"] == "3"
    assert list(objects.loc[""].to_frame().T["instances"]) == ["9"]
    counts = compare_object_counts(objects.reset_index())
    assert counts == {"changed": len(meta["changed_objects"]), "kept": 1, "dropped": 1,
                      "not_judged": len(meta["changed_objects"]) - 2, "false_kept": 2}
    table = read_compare_objects(tmp_path / "results")
    assert list(table["scene"].unique()) == ["tiny"]
    assert f"dropped {added} (support 0.20" in format_compare_objects(table)
    # candidates without positions (an older compare) or a scene folder that does not list
    # its objects: nothing to say
    kept.drop(columns=["x", "y", "z"]).to_csv(res / "change" / "changes.csv", index=False)
    assert compare_objects(res) is None
    kept.to_csv(res / "change" / "changes.csv", index=False)
    (res / "input" / "manifest.json").write_text(json.dumps({"scene": str(tmp_path)}))
    assert compare_objects(res) is None and len(read_compare_objects(tmp_path / "results")) == 0
