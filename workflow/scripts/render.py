"""Rule render: both paths at t=0 and t=1 -> EXR frames, previews, contact sheets."""
import _bootstrap  # noqa: F401  (gdiff from this checkout)
from pathlib import Path

from gdiff.options import from_config
from gdiff.sequence import RenderOptions, render_sequences
from gdiff.stage import run_stage

run_stage(snakemake, lambda: render_sequences(
    snakemake.input.model, snakemake.input.poses, Path(snakemake.output.index).parent,
    from_config(RenderOptions, snakemake.params.options, "render"),
    device=snakemake.params.device, scene_dir=snakemake.input.scene))
