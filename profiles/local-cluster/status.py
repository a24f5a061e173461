#!/usr/bin/env python3
"""Report a local-cluster job's state for Snakemake: running, success or failed."""
import os
import sys
from pathlib import Path

pid = sys.argv[1]
exit_file = Path(".snakemake/local-cluster") / f"{pid}.exit"
if exit_file.exists():
    print("success" if exit_file.read_text().strip() == "0" else "failed")
else:
    try:
        os.kill(int(pid), 0)
        print("running")
    except ProcessLookupError:
        print("failed")  # vanished without writing its exit status (killed)
