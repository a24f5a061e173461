#!/usr/bin/env python3
"""Submit a Snakemake job script as a detached local process; print its job id (the PID).

The job's console output goes to .snakemake/local-cluster/<pid>.out and its exit status to
<pid>.exit, which status.py reads.
"""
import os
import subprocess
import sys
from pathlib import Path

jobscript = sys.argv[-1]
folder = Path(".snakemake/local-cluster")
folder.mkdir(parents=True, exist_ok=True)
out = open(folder / "job.out.tmp", "ab")
proc = subprocess.Popen(
    ["bash", "-c", f'bash "{jobscript}"; echo $? > "{folder}/$$.exit.tmp" && '
                   f'mv "{folder}/$$.exit.tmp" "{folder}/$$.exit"'],
    stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
os.replace(folder / "job.out.tmp", folder / f"{proc.pid}.out")
print(proc.pid)
