"""Scene discovery (folder, folder of folders, sheet, synth) and validation errors."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from gdiff.errors import ConfigError, SceneError
from gdiff.scene import check_overrides, discover_scenes, validate_scene, write_manifest


def _img(path: Path, w=48, h=32, seed=0):
    rng = np.random.default_rng(seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), rng.integers(0, 255, (h, w, 3), dtype=np.uint8))


def make_scene(root: Path, n=3, eval_views=("000",), size=(48, 32)) -> Path:
    for s in ("before", "after"):
        for i in range(n):
            _img(root / s / f"{i:03d}.png", *size, seed=i)
    for v in eval_views:
        for k in ("before", "after", "masks"):
            _img(root / "eval" / k / f"{v}.png", *size)
    return root


def test_valid_scene_manifest(tmp_path):
    root = make_scene(tmp_path / "s")
    m = write_manifest(root, tmp_path / "out" / "manifest.json")
    assert (tmp_path / "out" / "manifest.json").exists()
    sets = [r["set"] for r in m["images"]]
    assert sets.count("before") == 3 and sets.count("after") == 3
    assert sets.count("eval_before") == sets.count("eval_after") == sets.count("eval_mask") == 1
    assert (m["width"], m["height"]) == (48, 32) and m["eval_views"] == ["000"]
    assert all(len(r["sha1"]) == 40 for r in m["images"])


def test_missing_before(tmp_path):
    root = make_scene(tmp_path / "s")
    for p in (root / "before").iterdir():
        p.unlink()
    (root / "before").rmdir()
    with pytest.raises(SceneError, match="missing folder before/"):
        validate_scene(root)


def test_empty_after(tmp_path):
    root = make_scene(tmp_path / "s")
    for p in (root / "after").iterdir():
        p.unlink()
    with pytest.raises(SceneError, match=r"after: no images"):
        validate_scene(root)


def test_too_few_images(tmp_path):
    root = make_scene(tmp_path / "s", n=2)
    with pytest.raises(SceneError, match="only 2 image"):
        validate_scene(root)


def test_corrupt_image_named(tmp_path):
    root = make_scene(tmp_path / "s")
    bad = root / "after" / "001.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n this is not really a png")
    with pytest.raises(SceneError, match=r"after/001.png: cannot be decoded"):
        validate_scene(root)


def test_mixed_sizes_recorded(tmp_path):
    """Photos of different sizes (other cameras) are accepted; the poses stage resamples them
    (tests/test_mixed.py)."""
    root = make_scene(tmp_path / "s")
    _img(root / "after" / "002.png", 64, 32)
    m = validate_scene(root)
    rec = next(r for r in m["images"] if r["path"] == "after/002.png")
    assert (rec["width"], rec["height"]) == (64, 32)
    assert m["sizes"] == [[48, 32], [64, 32]] and m["width"] is None


def test_eval_view_without_mask(tmp_path):
    root = make_scene(tmp_path / "s", eval_views=("000", "001"))
    (root / "eval" / "masks" / "001.png").unlink()
    with pytest.raises(SceneError, match="eval view '001' has before and after but no "
                                         "eval/masks/001"):
        validate_scene(root)


def test_eval_mask_without_images(tmp_path):
    root = make_scene(tmp_path / "s", eval_views=("000",))
    _img(root / "eval" / "masks" / "007.png")
    with pytest.raises(SceneError, match="mask\\(s\\) 007 have no"):
        validate_scene(root)


def test_one_sided_eval_view_allowed(tmp_path):
    root = make_scene(tmp_path / "s", eval_views=("000", "001"))
    (root / "eval" / "before" / "001.png").unlink()
    m = validate_scene(root)
    assert m["eval_views"] == ["000", "001"]
    assert [r["set"] for r in m["images"]].count("eval_before") == 1


def test_discover_single_folder_and_folder_of_scenes(tmp_path):
    a = make_scene(tmp_path / "bench" / "alpha")
    make_scene(tmp_path / "bench" / "beta", eval_views=())
    (tmp_path / "bench" / "notes").mkdir()
    one = discover_scenes(a)
    assert list(one) == ["alpha"] and one["alpha"].has_eval
    many = discover_scenes(tmp_path / "bench")
    assert sorted(many) == ["alpha", "beta"]
    assert many["alpha"].has_eval and not many["beta"].has_eval


def test_discover_synth():
    s = discover_scenes("synth:demo", synth_root="resources/synth")
    assert s["demo"].synth_preset == "demo" and s["demo"].path == Path("resources/synth/demo")
    assert s["demo"].synth_seed is None
    s = discover_scenes("synth:demo:3", synth_root="r")
    assert list(s) == ["demo_s3"] and s["demo_s3"].path == Path("r/demo_s3")
    assert (s["demo_s3"].synth_preset, s["demo_s3"].synth_seed) == ("demo", 3)
    with pytest.raises(ConfigError, match="whole number"):
        discover_scenes("synth:demo:x")


def test_sheet_with_synth_seeds(tmp_path):
    sheet = tmp_path / "scenes.tsv"
    sheet.write_text("name\tpath\n" "d0\tsynth:demo:0\n" "d1\tsynth:demo:1\n" "t\tsynth:tiny\n")
    s = discover_scenes(sheet)
    assert [(v.synth_preset, v.synth_seed, v.path.name) for v in s.values()] == [
        ("demo", 0, "demo_s0"), ("demo", 1, "demo_s1"), ("tiny", None, "tiny")]


def test_discover_sheet_with_overrides(tmp_path):
    make_scene(tmp_path / "data" / "desk")
    sheet = tmp_path / "scenes.tsv"
    sheet.write_text("name\tpath\tfit.max_side\tposes.source\n"
                     "desk1\tdata/desk\t160\t\n"
                     "desk2\tdata/desk\t\tknown\n")
    s = discover_scenes(sheet)
    assert s["desk1"].overrides == {"fit": {"max_side": 160}}
    assert s["desk2"].overrides == {"poses": {"source": "known"}}
    assert s["desk1"].path == tmp_path / "data" / "desk"


def test_sheet_overrides_must_name_configuration_keys(tmp_path):
    """A column the configuration does not have would be read and never used: an error naming
    the scene and the column (here a synthetic scene's view count, which is its preset's)."""
    import yaml

    schema = yaml.safe_load((Path(__file__).parents[1] / "workflow" / "schemas" /
                             "config.schema.yaml").read_text())
    make_scene(tmp_path / "data" / "desk")
    sheet = tmp_path / "scenes.tsv"
    sheet.write_text("name\tpath\tfit.max_side\tcompare.photo_agree\n"
                     "desk\tdata/desk\t160\t0\n")
    check_overrides(discover_scenes(sheet), schema)  # both known
    sheet.write_text("name\tpath\tsynth.n_before\n" "d6\tsynth:demo:0\t6\n")
    with pytest.raises(ConfigError, match=r"scene 'd6', column 'synth.n_before': 'synth' is not "
                                          r"a configuration section.*fit"):
        check_overrides(discover_scenes(sheet), schema)
    sheet.write_text("name\tpath\tfit.max_sid\n" "desk\tdata/desk\t160\n")
    with pytest.raises(ConfigError, match=r"'fit' has no key 'max_sid' \(its keys: .*max_side"):
        check_overrides(discover_scenes(sheet), schema)
    sheet.write_text("name\tpath\tfit.exposure\tcompare.photo_agree\n"
                     "desk\tdata/desk\tyes please\t0\n")
    with pytest.raises(ConfigError, match=r"column 'fit.exposure': 'yes please' is not of type "
                                          r"'boolean'"):
        check_overrides(discover_scenes(sheet), schema)
    sheet.write_text("name\tpath\tcompare.photo_agree\n" "desk\tdata/desk\t-1\n")
    with pytest.raises(ConfigError, match=r"column 'compare.photo_agree': -1 is less than the "
                                          r"minimum of 0"):
        check_overrides(discover_scenes(sheet), schema)


@pytest.mark.parametrize("content, match", [
    ("name\tfolder\nx\ty\n", "missing column.*path"),
    ("name\tpath\nx\tnowhere\n", "row 1: path nowhere is not a scene folder"),
    ("name\tpath\nbad name\tdata/desk\n", "row 1: scene name 'bad name'"),
    ("name\tpath\tmax_side\nx\tdata/desk\t3\n", "column 'max_side' is not of the form"),
    ("name\tpath\nx\tdata/desk\nx\tdata/desk\n", "row 2: scene name 'x' appears twice"),
])
def test_sheet_errors(tmp_path, content, match):
    make_scene(tmp_path / "data" / "desk")
    sheet = tmp_path / "scenes.tsv"
    sheet.write_text(content)
    with pytest.raises(ConfigError, match=match):
        discover_scenes(sheet)


def test_discover_errors(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        discover_scenes(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ConfigError, match="neither a scene folder"):
        discover_scenes(tmp_path / "empty")
