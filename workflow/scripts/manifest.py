"""Rule manifest: validate the scene folder and list its images (frames picked from videos)."""
import _bootstrap  # noqa: F401  (gdiff from this checkout)
from gdiff.options import from_config
from gdiff.scene import write_manifest
from gdiff.stage import run_stage
from gdiff.video import InputOptions

run_stage(snakemake, lambda: write_manifest(
    snakemake.input[0], snakemake.output[0],
    from_config(InputOptions, snakemake.params.options, "input")))
