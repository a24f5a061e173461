"""Rule fit: one 4D Gaussian model, before images at t=0 and after images at t=1."""
import _bootstrap  # noqa: F401  (gdiff from this checkout)
from pathlib import Path

from gdiff.options import from_config
from gdiff.splat.train import FitOptions, fit_scene
from gdiff.stage import run_stage

run_stage(snakemake, lambda: fit_scene(
    snakemake.input.scene, snakemake.input.cameras, snakemake.input.points,
    Path(snakemake.output.model).parent, from_config(FitOptions, snakemake.params.options, "fit"),
    device=snakemake.params.device))
