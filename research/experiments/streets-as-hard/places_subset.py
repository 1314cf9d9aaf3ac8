"""A copy of a real run holding only the places a world run's streets stand for: the real side
of the issue's targets set on the places the grid holds (question (b) in
docs/experiments/streets_as_hard.md), for `falsify agreement WORLD OUT`.

  python research/experiments/streets-as-hard/places_subset.py WORLD_RUN REAL_RUN OUT
"""

from __future__ import annotations

import shutil
import sqlite3
import sys
from pathlib import Path

from falsify.jobs.agreement import _bg_name, _bg_place, ok_rows
from falsify.results.store import STORE_NAME, open_run


def subset(world_run: str, real_run: str, out: str) -> tuple[int, int]:
    """Write OUT: REAL_RUN's store without the rows of places no street of WORLD_RUN stands
    for; (places kept, rows dropped)."""
    world, real = open_run(world_run), open_run(real_run)
    wanted = {_bg_place(world, bg) for bg in ok_rows(world)["background"].unique()}
    wanted.discard(None)
    if not wanted:
        raise SystemExit(f"{world_run}: its streets stand for no real place")
    drop = [int(bg) for bg in real.frame["background"].unique() if _bg_name(real, bg) not in wanted]
    dest = Path(out)
    if dest.exists():
        raise SystemExit(f"{dest}: exists; choose a new folder")
    dest.mkdir(parents=True)
    shutil.copy(Path(real_run) / STORE_NAME, dest / STORE_NAME)
    if not drop:    # the streets stand for every place the real run holds
        return len(wanted), 0
    with sqlite3.connect(dest / STORE_NAME) as db:
        n = db.execute(f"DELETE FROM samples WHERE background IN ({','.join('?' * len(drop))})",
                       drop).rowcount
    return len(wanted), n


if __name__ == "__main__":
    if len(sys.argv) != 4:
        raise SystemExit(__doc__)
    kept, dropped = subset(*sys.argv[1:])
    print(f"{sys.argv[3]}: {kept} places kept, {dropped} rows dropped")
