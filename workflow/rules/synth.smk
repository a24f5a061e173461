# Built-in synthetic scenes (scenes: synth:<preset> or synth:<preset>:<seed>), generated into
# resources/synth/<preset> (seed: config synth_seed) or resources/synth/<preset>_s<seed>.

SYNTH = {
    s.path.name: (s.synth_preset, s.synth_seed)
    for s in SCENES.values()
    if s.synth_preset is not None
}


def synth_params(wildcards):
    preset, seed = SYNTH[wildcards.synth]
    return {"preset": preset, "seed": config["synth_seed"] if seed is None else seed}


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
    conda:
        "../envs/gdiff.yaml"
    log:
        "logs/{scene}/manifest.log",
    benchmark:
        res("{scene}", "benchmarks", "manifest.tsv")
    script:
        "../scripts/manifest.py"
