"""Rule poses: register all images in one frame (COLMAP) or import known poses."""
import _bootstrap  # noqa: F401  (gdiff from this checkout)
from pathlib import Path

from gdiff.io import read_json
from gdiff.options import from_config
from gdiff.scene import manifest_image_root
from gdiff.sfm import PosesOptions, run_poses
from gdiff.stage import run_stage


def main():
    opts = from_config(PosesOptions, snakemake.params.options, "poses")
    manifest = read_json(snakemake.input.manifest)
    images = [(r["path"], r["set"]) for r in manifest["images"] if r["set"] != "eval_mask"]
    root = manifest_image_root(snakemake.input.manifest, snakemake.input.scene)
    return run_poses(snakemake.input.scene, Path(snakemake.output.cameras).parent, opts,
                     images=images, image_root=root)


run_stage(snakemake, main)
