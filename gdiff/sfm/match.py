"""SIFT matching of image pairs that gives the same matches on every run.

COLMAP's CPU matcher (pycolmap 4.2) now and then loses matches when two matchers run at once in
one process: a run on two threads may leave a pair or two with fewer matches or none, and the
poses move. Two matchers on separate databases in two threads of one process do it too, so the
shared state is inside the library; one matcher thread gives the same matches every time. So,
for repeatable runs, the pairs are split among worker *processes* that each match their share
on one thread into their own copy of the database (:func:`match_in_processes`); the matches
are merged into the database, and the geometric verification (whose RANSAC is seeded per pair,
and which gives the same result on any number of threads) runs once over all of them.

Run as ``python -m gdiff.sfm.match DATABASE PAIRS_FILE`` it is one such worker.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

from ..errors import PosesError


def worker_count(num_threads: int, n_pairs: int) -> int:
    """Worker processes for ``n_pairs`` pairs with ``num_threads`` (-1 = every CPU this process
    may use), at least 1 and at most one per pair."""
    if num_threads is None or num_threads <= 0:
        try:
            num_threads = len(os.sched_getaffinity(0))
        except AttributeError:  # pragma: no cover - not on Linux
            num_threads = os.cpu_count() or 1
    return max(1, min(int(num_threads), n_pairs))


def all_pairs(db: Path) -> list[tuple[str, str]]:
    """Every pair of the database's images (by image id), as exhaustive matching takes them."""
    with contextlib.closing(sqlite3.connect(db)) as con:
        names = [n for (n,) in con.execute("SELECT name FROM images ORDER BY image_id")]
    return [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]


def match_in_processes(db: Path, work: Path, pairs: list[tuple[str, str]],
                       num_threads: int, quiet: bool = True) -> int:
    """Match ``pairs`` (image names) into ``db``'s ``matches`` table, without verification.

    The pairs are dealt round-robin to :func:`worker_count` processes; each copies ``db``
    into ``work`` and matches its share there on one thread; their tables are then merged into
    ``db``. Returns the number of workers.

    Raises:
        PosesError: a worker failed (its last output lines are in the message).
    """
    if not pairs:
        return 0
    n = worker_count(num_threads, len(pairs))
    env = dict(os.environ, GDIFF_COLMAP_QUIET="1" if quiet else "0")
    jobs = []
    try:
        for k in range(n):
            part_db = work / f"match_part{k}.db"
            part_pairs = work / f"match_part{k}.txt"
            shutil.copyfile(db, part_db)
            part_pairs.write_text("".join(f"{a} {b}\n" for a, b in pairs[k::n]))
            err = open(work / f"match_part{k}.log", "w+b")
            try:
                proc = subprocess.Popen([sys.executable, "-m", __name__, str(part_db),
                                         str(part_pairs)], stdout=err,
                                        stderr=subprocess.STDOUT, env=env)
            except BaseException:
                err.close()
                raise
            jobs.append((proc, err, part_db))
        for proc, err, _ in jobs:
            if proc.wait() != 0:
                err.seek(0)
                tail = err.read().decode(errors="replace").strip().splitlines()[-5:]
                raise PosesError("COLMAP feature matching failed in a worker process "
                                 f"(exit code {proc.returncode}):\n  " + "\n  ".join(tail))
    finally:
        for proc, err, _ in jobs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            err.close()
    with contextlib.closing(sqlite3.connect(db, isolation_level=None)) as con:
        for _, _, part_db in jobs:
            con.execute("ATTACH DATABASE ? AS part", (str(part_db),))
            con.execute("BEGIN")
            con.execute("INSERT OR REPLACE INTO matches SELECT * FROM part.matches")
            con.execute("COMMIT")
            con.execute("DETACH DATABASE part")
            part_db.unlink()
    return n


def _worker(db: str, pairs_file: str) -> None:
    import pycolmap

    if os.environ.get("GDIFF_COLMAP_QUIET", "1") == "1":
        pycolmap.logging.minloglevel = max(pycolmap.logging.minloglevel, 1)
    mo = pycolmap.FeatureMatchingOptions()
    mo.num_threads = 1
    mo.skip_geometric_verification = True
    po = pycolmap.ImportedPairingOptions()
    po.match_list_path = pairs_file
    pycolmap.match_image_pairs(db, matching_options=mo, pairing_options=po,
                               device=pycolmap.Device.cpu)


if __name__ == "__main__":
    _worker(sys.argv[1], sys.argv[2])
