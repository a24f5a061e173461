"""Rule synth: generate a built-in synthetic scene."""
import _bootstrap  # noqa: F401  (gdiff from this checkout)
from gdiff.stage import run_stage
from gdiff.synth import make_scene

run_stage(snakemake, lambda: make_scene(snakemake.output[0],
                                        preset=snakemake.params.synth["preset"],
                                        seed=snakemake.params.synth["seed"], overwrite=True))
