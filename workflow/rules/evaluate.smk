# Score the learned change maps and the baselines at the eval views; summarise all scenes.


rule evaluate:
    input:
        scene=scene_dir,
        manifest=res("{scene}", "input", "manifest.json"),
        cameras=res("{scene}", "poses", "cameras.json"),
        partition=res("{scene}", "partition", "model.pt"),
        evidence=res("{scene}", "change", "evidence3d.npz"),
        keyframes=res("{scene}", "change", "keyframes.csv"),
    output:
        metrics=report(
            res("{scene}", "eval", "metrics.csv"),
            caption="../report/metrics.rst",
            category="{scene}",
            subcategory="metrics",
            labels={"table": "per view"},
        ),
        scene_summary=report(
            res("{scene}", "eval", "scene_summary.csv"),
            caption="../report/scene_summary.rst",
            category="{scene}",
            subcategory="metrics",
            labels={"table": "per method"},
        ),
        overlays=report(
            directory(res("{scene}", "eval", "overlays")),
            patterns=["{view}.png"],
            caption="../report/overlays.rst",
            category="{scene}",
            subcategory="eval views",
            labels={"view": "{view}"},
        ),
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
        summary=report(
            "results/summary.csv",
            caption="../report/summary.rst",
            category="summary",
            labels={"table": "scene x method"},
        ),
        timings=report(
            "results/timings.csv",
            caption="../report/timings.rst",
            category="summary",
            labels={"table": "timings"},
        ),
        plots=report(
            directory("results/plots"),
            patterns=["{metric}.png"],
            caption="../report/plots.rst",
            category="summary",
            labels={"plot": "{metric}"},
        ),
    params:
        benchmarks={s: res(s, "benchmarks") for s in SCENES},
    conda:
        "../envs/gdiff.yaml"
    log:
        "logs/summary.log",
    script:
        "../scripts/summary.py"
