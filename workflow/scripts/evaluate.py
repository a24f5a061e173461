"""Rule evaluate: learned change maps and baselines, scored at the scene's eval views."""
import _bootstrap  # noqa: F401  (gdiff from this checkout)
from pathlib import Path

from gdiff.evaluate import EvalOptions, evaluate_workflow_scene
from gdiff.options import from_config
from gdiff.stage import run_stage

run_stage(snakemake, lambda: evaluate_workflow_scene(
    scene_dir=snakemake.input.scene, cameras_json=snakemake.input.cameras,
    partition_model=snakemake.input.partition, out_dir=Path(snakemake.output.metrics).parent,
    scene_name=snakemake.wildcards.scene,
    options=from_config(EvalOptions, snakemake.params.options, "evaluate"),
    segment_options=snakemake.params.segment, device=snakemake.params.device,
    evidence=snakemake.input.evidence, keyframes=snakemake.input.keyframes))
