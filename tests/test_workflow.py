"""The Snakemake workflow parses, lints clean, validates its config and finds scenes."""

import shutil
import subprocess
import sys
from pathlib import Path


ROOT = Path(__file__).resolve().parents[1]
SNAKEMAKE = shutil.which("snakemake") or str(Path(sys.executable).parent / "snakemake")


def smk(*args, cwd=ROOT):
    return subprocess.run([SNAKEMAKE, "--cores", "1", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=300)


def test_lint_clean():
    r = smk("--lint")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "good condition" in r.stdout + r.stderr


def test_dry_run_default_demo_lists_every_stage(tmp_path):
    # in an empty working folder: the results of a `make demo` in the checkout would leave
    # nothing to do there
    r = smk("-s", str(ROOT / "Snakefile"), "-d", str(tmp_path), "-n", cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    for rule in ("synth", "manifest", "poses", "fit", "interpolate", "render", "segment",
                 "compare", "partition", "evaluate", "summary"):
        assert f"rule {rule}:" in r.stdout, rule


def test_unknown_config_key_is_named():
    r = smk("-n", "--config", "scnes=synth:tiny")
    assert r.returncode != 0
    assert "unknown key 'scnes'" in r.stdout + r.stderr


def test_bad_config_value_is_rejected():
    r = smk("-n", "--config", "device=tpu")
    assert r.returncode != 0
    assert "device" in r.stdout + r.stderr


def test_nested_command_line_config_is_typed():
    """--config fit='{exposure: true}' (Snakemake hands the workflow the string 'true')."""
    r = smk("-n", "--config", "fit={exposure: true, max_side: 64}")
    assert r.returncode == 0, r.stdout + r.stderr
    r = smk("-n", "--config", "fit={exposure: yes please}")
    assert r.returncode != 0
    assert "fit.exposure = 'yes please' is not boolean" in r.stdout + r.stderr


def test_missing_scene_folder_is_named(tmp_path):
    r = smk("-n", "--config", f"scenes={tmp_path / 'nope'}")
    assert r.returncode != 0
    assert "does not exist" in r.stdout + r.stderr


def test_folder_of_scenes_and_sheet(tmp_path):
    from test_scene import make_scene

    make_scene(tmp_path / "bench" / "a")
    make_scene(tmp_path / "bench" / "b", eval_views=())
    r = smk("-n", "--config", f"scenes={tmp_path / 'bench'}")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "results/a/eval/metrics.csv" in r.stdout
    assert "results/b/partition/model.pt" in r.stdout
    assert "results/b/eval/metrics.csv" not in r.stdout  # b has no eval/ folder
    sheet = tmp_path / "scenes.tsv"
    sheet.write_text("name\tpath\tfit.max_side\nfirst\tbench/a\t64\n")
    r = smk("-n", "--config", f"scenes={sheet}")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "results/first/fit/model.pt" in r.stdout


def test_bad_input_fails_with_message_and_no_output(tmp_path):
    """A corrupt photo stops the first rule with a message naming it; nothing half-written."""
    from test_scene import make_scene

    scene = make_scene(tmp_path / "data" / "broken")
    (scene / "after" / "001.png").write_bytes(b"\x89PNG\r\n\x1a\nnot an image")
    work = tmp_path / "work"
    work.mkdir()
    r = subprocess.run([SNAKEMAKE, "-s", str(ROOT / "Snakefile"), "-d", str(work), "--cores",
                        "1", "--config", f"scenes={scene}", "--",
                        "results/broken/input/manifest.json"],
                       cwd=work, capture_output=True, text=True, timeout=300)
    out = r.stdout + r.stderr
    assert r.returncode != 0
    assert "after/001.png: cannot be decoded as an image" in out
    assert "Traceback" not in out
    assert not (work / "results/broken/input/manifest.json").exists()
    assert not list((work / "results").rglob("*.tmp*")) if (work / "results").exists() else True
