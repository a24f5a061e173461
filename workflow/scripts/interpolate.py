"""Rule interpolate: slerp/lerp camera paths through the before and the after poses."""
import _bootstrap  # noqa: F401  (gdiff from this checkout)
from gdiff.interpolate import InterpolateOptions, build_sequence
from gdiff.options import from_config
from gdiff.stage import run_stage

run_stage(snakemake, lambda: build_sequence(
    snakemake.input.cameras, snakemake.output.poses,
    from_config(InterpolateOptions, snakemake.params.options, "interpolate")))
