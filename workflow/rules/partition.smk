# Classification encoding per Gaussian -> changed / unchanged Gaussians, change maps anywhere.


rule partition:
    input:
        scene=scene_dir,
        model=res("{scene}", "fit", "model.pt"),
        cameras=res("{scene}", "poses", "cameras.json"),
        keyframes=res("{scene}", "change", "keyframes.csv"),
    output:
        model=res("{scene}", "partition", "model.pt"),
        changed=res("{scene}", "partition", "changed.ply"),
        unchanged=res("{scene}", "partition", "unchanged.ply"),
        maps=report(
            directory(res("{scene}", "partition", "maps", "overlay")),
            patterns=["{name}.png"],
            caption="../report/change_maps.rst",
            category="{scene}",
            subcategory="change maps at the key poses",
            labels={"view": "{name}"},
        ),
    params:
        options=options("partition"),
        device=config["device"],
    threads: 2
    resources:
        gpu=GPU,
    conda:
        "../envs/gdiff.yaml"
    log:
        "logs/{scene}/partition.log",
    benchmark:
        res("{scene}", "benchmarks", "partition.tsv")
    script:
        "../scripts/partition.py"
