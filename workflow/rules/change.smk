# Instance segmentation + tracking with one ID space, then ID comparison -> change masks.


rule segment:
    input:
        index=res("{scene}", "render", "frames.json"),
        frames=frame_dirs,
        poses=res("{scene}", "sequence", "poses.json"),
    output:
        index=res("{scene}", "instances", "index.json"),
        tracks=res("{scene}", "instances", "tracks.csv"),
    params:
        segment=options("segment"),
        track=options("track"),
    threads: 2
    conda:
        "../envs/gdiff.yaml"
    log:
        "logs/{scene}/segment.log",
    benchmark:
        res("{scene}", "benchmarks", "segment.tsv")
    script:
        "../scripts/segment.py"


rule compare:
    input:
        scene=scene_dir,
        index=res("{scene}", "instances", "index.json"),
        frames=frame_dirs,
        poses=res("{scene}", "sequence", "poses.json"),
    output:
        keyframes=res("{scene}", "change", "keyframes.csv"),
        changes=res("{scene}", "change", "changes.csv"),
        candidates=res("{scene}", "change", "candidates.csv"),
        evidence=res("{scene}", "change", "evidence3d.npz"),
        coverage=res("{scene}", "change", "coverage.csv"),
    params:
        options=options("compare"),
    threads: 2
    conda:
        "../envs/gdiff.yaml"
    log:
        "logs/{scene}/compare.log",
    benchmark:
        res("{scene}", "benchmarks", "compare.tsv")
    script:
        "../scripts/compare.py"
