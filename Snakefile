# gdiff: Gaussian Difference change detection workflow.
#   snakemake --cores 2                                  # the built-in demo scene
#   snakemake --cores 2 --config scenes=/data/bench      # every scene folder in /data/bench
# See README.md for inputs, configuration and outputs.
import os
import sys

from snakemake.utils import min_version

min_version("9.0")

sys.path.insert(0, workflow.basedir)  # gdiff importable from a plain checkout, too


# The defaults; --configfile FILE and --config KEY=VALUE override them.
configfile: os.path.join(workflow.basedir, "config", "config.yaml")


report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"
include: "workflow/rules/synth.smk"
include: "workflow/rules/poses.smk"
include: "workflow/rules/fit.smk"
include: "workflow/rules/sequence.smk"
include: "workflow/rules/change.smk"
include: "workflow/rules/partition.smk"
include: "workflow/rules/evaluate.smk"


rule all:
    input:
        all_targets(),
    default_target: True
