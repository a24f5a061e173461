"""Rule summary: one table of all scenes x methods, timings per rule, plots."""
import _bootstrap  # noqa: F401  (gdiff from this checkout)
from pathlib import Path

from gdiff.stage import run_stage
from gdiff.summary import summarize

benchmarks = {(scene, p.stem): p for scene, folder in snakemake.params.benchmarks.items()
              for p in sorted(Path(folder).glob("*.tsv"))}
run_stage(snakemake, lambda: summarize(list(snakemake.input.metrics), benchmarks,
                                       Path(snakemake.output.summary).parent))
