# Built-in synthetic scenes (scenes: synth:<preset> or synth:<preset>:<seed>), generated into
# resources/synth/<preset> (seed: config synth_seed) or resources/synth/<preset>_s<seed>
# (SYNTH and synth_params in common.smk).

rule synth:
    wildcard_constraints:
        synth="|".join(map(re.escape, SYNTH)) if SYNTH else "[^/]+",
    output:
        directory("resources/synth/{synth}"),
    params:
        synth=synth_params,
    conda:
        "../envs/gdiff.yaml"
    log:
        "logs/synth/{synth}.log",
    benchmark:
        "results/benchmarks/synth_{synth}.tsv"
    script:
        "../scripts/synth.py"


rule manifest:
    input:
        scene_dir,
    output:
        res("{scene}", "input", "manifest.json"),
    params:
        options=options("input"),
    conda:
        "../envs/gdiff.yaml"
    log:
        "logs/{scene}/manifest.log",
    benchmark:
        res("{scene}", "benchmarks", "manifest.tsv")
    script:
        "../scripts/manifest.py"
