"""Rule compare: IDs present at one time only -> change masks per pose and time."""
import _bootstrap  # noqa: F401  (gdiff from this checkout)
from pathlib import Path

from gdiff.cameras import image_root
from gdiff.compare import CompareOptions, compare
from gdiff.options import from_config
from gdiff.stage import run_stage

run_stage(snakemake, lambda: compare(
    Path(snakemake.input.index).parent, snakemake.input.poses,
    Path(snakemake.output.keyframes).parent,
    from_config(CompareOptions, snakemake.params.options, "compare"),
    workers=snakemake.threads,
    photo_root=image_root(snakemake.input.scene, snakemake.input.poses)))
