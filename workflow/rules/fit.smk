# One 4D Gaussian model over both times (before at t=0, after at t=1). Resumes from fit/ckpt/.


rule fit:
    input:
        scene=scene_dir,
        cameras=res("{scene}", "poses", "cameras.json"),
        points=res("{scene}", "poses", "points.ply"),
    output:
        model=res("{scene}", "fit", "model.pt"),
        ply_t0=res("{scene}", "fit", "gaussians_t0.ply"),
        ply_t1=res("{scene}", "fit", "gaussians_t1.ply"),
        train_log=res("{scene}", "fit", "train_log.csv"),
        quality=res("{scene}", "fit", "quality.csv"),
    params:
        options=options("fit"),
        device=config["device"],
    threads: 2
    resources:
        gpu=GPU,
    conda:
        "../envs/gdiff.yaml"
    log:
        "logs/{scene}/fit.log",
    benchmark:
        res("{scene}", "benchmarks", "fit.tsv")
    script:
        "../scripts/fit.py"
