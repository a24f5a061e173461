"""Summary aggregation across two scenes, timings from benchmark TSVs, plots."""

import math

import numpy as np
import pandas as pd
import pytest

from gdiff import metrics as M
from gdiff.errors import SceneError
from gdiff.io import read_image, write_csv
from gdiff.summary import find_benchmarks, read_benchmark, summarize

BENCH_HEADER = "s\th:m:s\tmax_rss\tmax_vms\tmax_uss\tmax_pss\tio_in\tio_out\tmean_load\tcpu_time\n"


def _rect(*rects, h=20, w=20):
    m = np.zeros((h, w), bool)
    for x0, y0, x1, y1 in rects:
        m[y0:y1, x0:x1] = True
    return m


def _scene_csv(root, scene, views):
    """views: {view: (gt, {method: pred})} -> results/<scene>/eval/{metrics,boxes}.csv"""
    rows, boxes = [], []
    for view, (gt, preds) in views.items():
        for method, pred in preds.items():
            s, b = M.score_view(pred, gt)
            s.update(M.object_scores(pred, M.object_regions(gt)))
            rows.append({"scene": scene, "view": view, "method": method, **s, "seconds": 0.1})
            boxes.append(b.assign(scene=scene, view=view, method=method))
    out = root / scene / "eval"
    write_csv(out / "metrics.csv", pd.DataFrame(rows))
    write_csv(out / "boxes.csv", pd.concat(boxes, ignore_index=True))
    return out / "metrics.csv"


def test_summary_two_scenes(tmp_path):
    gt = _rect((0, 0, 10, 10))  # 100 px
    a = _scene_csv(tmp_path, "alpha", {
        "000": (gt, {"good": gt, "bad": _rect((0, 0, 5, 10))}),          # bad: TP 50, FN 50
        "001": (_rect(), {"good": _rect(), "bad": _rect((15, 15, 20, 20))}),  # empty GT
    })
    b = _scene_csv(tmp_path, "beta", {
        "000": (gt, {"good": _rect((0, 0, 10, 5)), "bad": _rect((10, 10, 20, 20))}),
    })
    bench = {}
    for scene, rule, lines in (("alpha", "fit", ["10.0\t0:00:10\t500.5", "14.0\t0:00:14\t700.0"]),
                               ("alpha", "evaluate", ["2.5\t0:00:02\tNA"]),
                               ("beta", "fit", ["8.0\t0:00:08\t400.0"])):
        p = tmp_path / "benchmarks" / scene / f"{rule}.tsv"
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(BENCH_HEADER + "".join(
            f"{ln}\t900\t400\t400\t1\t2\t0.5\t{float(ln.split()[0]) * 0.9}\n" for ln in lines))
        bench[(scene, rule)] = p
    assert find_benchmarks({s: tmp_path / "benchmarks" / s for s in ("alpha", "beta")}) == bench
    res = summarize([a, b], bench, tmp_path / "results")
    s = pd.read_csv(tmp_path / "results" / "summary.csv").set_index(["scene", "method"])
    assert set(s.index) == {("alpha", "good"), ("alpha", "bad"), ("beta", "good"),
                            ("beta", "bad"), ("ALL", "good"), ("ALL", "bad")}
    # alpha/bad: view 000 P 1 R .5 ; view 001 P 0, R undefined -> R mean .5 over 1 view
    ab = s.loc[("alpha", "bad")]
    assert ab["P_mean"] == pytest.approx(0.5) and ab["R_mean"] == pytest.approx(0.5)
    assert ab["n_R"] == 1 and ab["n_views"] == 2
    # pooled alpha/bad: TP 50, FP 25, FN 50
    assert (ab["TP"], ab["FP"], ab["FN"]) == (50, 25, 50)
    assert ab["IoU_pooled"] == pytest.approx(50 / 125)
    # alpha/good: the empty view is undefined everywhere; pooled = perfect
    ag = s.loc[("alpha", "good")]
    assert ag["F1_pooled"] == 1.0 and ag["n_F1"] == 1
    # ALL/good: mean over scenes of per-scene means (1.0 and 0.5 IoU) vs pooled over views
    allg = s.loc[("ALL", "good")]
    assert allg["IoU_mean"] == pytest.approx((1.0 + 0.5) / 2)
    assert allg["IoU_pooled"] == pytest.approx(150 / 200)
    assert allg["n_views"] == 3 and allg["n_scenes"] == 2
    # box AP pooled over both scenes for "bad": alpha box (0,0,5,10) IoU .5 -> TP;
    # alpha 001 false box; beta false box -> 1 TP of 2 GT boxes
    allb = s.loc[("ALL", "bad")]
    assert allb["box_TP"] == 1 and allb["box_FN"] == 1 and allb["box_FP"] == 2
    assert allb["box_R_pooled"] == 0.5
    # object recall pooled over both scenes: "bad" covers half of alpha's object (found) and
    # nothing of beta's -> 1 of 2; "good" covers half of beta's -> 2 of 2
    assert allb["obj_N"] == 2 and allb["obj_R_pooled"] == 0.5
    assert allg["obj_R_pooled"] == 1.0 and s.loc[("beta", "bad"), "obj_R_pooled"] == 0.0
    assert 0 < allb["box_AP_pooled"] <= 0.5
    assert s.loc[("beta", "bad"), "P_mean"] == 0.0

    t = pd.read_csv(tmp_path / "results" / "timings.csv")
    assert t[["scene", "rule"]].values.tolist() == [["alpha", "evaluate"], ["alpha", "fit"],
                                                  ["beta", "fit"]]
    fit = t[(t.scene == "alpha") & (t.rule == "fit")].iloc[0]
    assert fit["seconds"] == 12.0 and fit["max_rss_mb"] == 700.0 and fit["repeats"] == 2
    assert fit["cpu_seconds"] == pytest.approx(10.8)
    assert math.isnan(t[(t.rule == "evaluate")].iloc[0]["max_rss_mb"])

    names = sorted(p.name for p in (tmp_path / "results" / "plots").iterdir())
    assert "F1_pooled.png" in names and "timings.png" in names and "box_AP_pooled.png" in names
    img = read_image(tmp_path / "results" / "plots" / "F1_pooled.png")
    assert img.shape[0] > 100 and img.std() > 0.05
    assert len(res["plots"]) == len(names)


def test_summary_errors_name_files(tmp_path):
    with pytest.raises(SceneError, match="nope/metrics.csv"):
        summarize([tmp_path / "nope" / "metrics.csv"], {}, tmp_path / "r")
    bad = tmp_path / "b.tsv"
    bad.write_text("x\ty\n1\t2\n")
    with pytest.raises(SceneError, match="b.tsv"):
        read_benchmark(bad)
