# Interpolated camera paths (P~1 before poses, P~2 after poses) rendered at t=0 and t=1.


rule interpolate:
    input:
        cameras=res("{scene}", "poses", "cameras.json"),
    output:
        poses=res("{scene}", "sequence", "poses.json"),
    params:
        options=options("interpolate"),
    conda:
        "../envs/gdiff.yaml"
    log:
        "logs/{scene}/interpolate.log",
    benchmark:
        res("{scene}", "benchmarks", "interpolate.tsv")
    script:
        "../scripts/interpolate.py"


rule render:
    input:
        scene=scene_dir,
        model=res("{scene}", "fit", "model.pt"),
        poses=res("{scene}", "sequence", "poses.json"),
    output:
        index=res("{scene}", "render", "frames.json"),
        frames=[frames_output(res("{scene}", "render", path, t)) for path, t in FRAME_DIRS],
        sheets=[
            report(
                res("{scene}", "render", path, f"{t}_sheet.png"),
                caption="../report/sheets.rst",
                category="{scene}",
                subcategory="rendered sequences",
                labels={"path": path, "time": t},
            )
            for path, t in FRAME_DIRS
        ],
    params:
        options=options("render"),
        device=config["device"],
    threads: 2
    resources:
        gpu=GPU,
    conda:
        "../envs/gdiff.yaml"
    log:
        "logs/{scene}/render.log",
    benchmark:
        res("{scene}", "benchmarks", "render.tsv")
    script:
        "../scripts/render.py"
