"""Rule segment: instance segmentation of every rendered frame + tracking in one ID space."""
import _bootstrap  # noqa: F401  (gdiff from this checkout)
from dataclasses import replace
from pathlib import Path

from gdiff.options import from_config
from gdiff.segment import SegmentOptions, segment_and_track
from gdiff.stage import run_stage
from gdiff.track import TrackOptions


def main():
    seg = from_config(SegmentOptions, snakemake.params.segment, "segment")
    if seg.threads == 0:  # SAM's onnxruntime: the rule's threads, not every core
        seg = replace(seg, threads=snakemake.threads)
    return segment_and_track(
        Path(snakemake.input.index).parent, snakemake.input.poses,
        Path(snakemake.output.index).parent, seg,
        from_config(TrackOptions, snakemake.params.track, "track"), workers=snakemake.threads)


run_stage(snakemake, main)
