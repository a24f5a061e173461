# Register before, after and eval images in one frame (COLMAP) or import known poses.


rule poses:
    input:
        scene=scene_dir,
        manifest=res("{scene}", "input", "manifest.json"),
    output:
        cameras=res("{scene}", "poses", "cameras.json"),
        points=res("{scene}", "poses", "points.ply"),
    params:
        options=options("poses"),
    threads: 2
    conda:
        "../envs/gdiff.yaml"
    log:
        "logs/{scene}/poses.log",
    benchmark:
        res("{scene}", "benchmarks", "poses.tsv")
    script:
        "../scripts/poses.py"
