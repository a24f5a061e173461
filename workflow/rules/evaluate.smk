# Score the learned change maps and the baselines at the eval views; summarise all scenes.


rule evaluate:
    input:
        scene=scene_dir,
        manifest=res("{scene}", "input", "manifest.json"),
        cameras=res("{scene}", "poses", "cameras.json"),
        partition=res("{scene}", "partition", "model.pt"),
    output:
        metrics=res("{scene}", "eval", "metrics.csv"),
    params:
        options=options("evaluate"),
        segment=options("segment"),
        device=config["device"],
    threads: 2
    conda:
        "../envs/gdiff.yaml"
    log:
        "logs/{scene}/evaluate.log",
    benchmark:
        res("{scene}", "benchmarks", "evaluate.tsv")
    script:
        "../scripts/evaluate.py"


rule summary:
    input:
        metrics=[res(s, "eval", "metrics.csv") for s in SCENES if SCENES[s].has_eval],
    output:
        summary="results/summary.csv",
        timings="results/timings.csv",
    params:
        benchmarks={s: res(s, "benchmarks") for s in SCENES},
    conda:
        "../envs/gdiff.yaml"
    log:
        "logs/summary.log",
    script:
        "../scripts/summary.py"
