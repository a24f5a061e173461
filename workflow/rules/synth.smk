# Built-in synthetic scenes (scenes: synth:<preset>), generated into resources/synth/.


rule synth:
    output:
        directory("resources/synth/{preset}"),
    params:
        seed=config["synth_seed"],
    conda:
        "../envs/gdiff.yaml"
    log:
        "logs/synth/{preset}.log",
    benchmark:
        "results/benchmarks/synth_{preset}.tsv"
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
