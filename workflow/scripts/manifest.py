"""Rule manifest: validate the scene folder and list its images."""
import _bootstrap  # noqa: F401  (gdiff from this checkout)
from gdiff.scene import write_manifest
from gdiff.stage import run_stage

run_stage(snakemake, lambda: write_manifest(snakemake.input[0], snakemake.output[0]))
