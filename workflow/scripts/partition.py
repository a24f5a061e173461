"""Rule partition: learn which Gaussians changed; change maps at the key poses."""
import _bootstrap  # noqa: F401  (gdiff from this checkout)
from pathlib import Path

from gdiff.options import from_config
from gdiff.partition import PartitionOptions, train_partition
from gdiff.stage import run_stage

run_stage(snakemake, lambda: train_partition(
    snakemake.input.model, snakemake.input.cameras, snakemake.input.keyframes,
    snakemake.input.scene, Path(snakemake.output.model).parent,
    from_config(PartitionOptions, snakemake.params.options, "partition"),
    device=snakemake.params.device))
