#!/usr/bin/env python
"""A/B of loading and building a medium: two checkouts of mi-amr, fresh
processes alternating (old, new, old, new, ...), on one data file.

    DRJIT_LIBLLVM_PATH="$(tools/find-llvm19)" .venv/bin/python tools/ab_load.py FILE \\
        [--old REV] [--reconstruction tent] [--rounds 2]

"old" is commit ``--rev`` checked out with ``git worktree`` into a temporary
folder, "new" the work tree; each process imports the side's ``mi_amr``
(``PYTHONPATH``) and times one ``mi.load_dict`` of an ``amr`` medium with
the default structures (wall and CPU seconds, cells per second, the build
seconds of each structure). Same Python environment for both sides.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ONE = r"""
import json, sys, time
from mi_amr._llvm import ensure_llvm_path
ensure_llvm_path()
import mitsuba as mi
mi.set_variant("llvm_ad_rgb")
import mi_amr
t0, c0 = time.perf_counter(), time.process_time()
med = mi.load_dict({"type": "amr", "filename": sys.argv[1], "reconstruction": sys.argv[2],
                    "transfer_function": "spiky", "density_scale": 60.0})
t = time.perf_counter() - t0
print(json.dumps({"cells": len(med.volume), "wall_s": t, "cpu_s": time.process_time() - c0,
                  "cells_per_s": len(med.volume) / t, "block": med.volume.block,
                  "build_s": dict(med.build_seconds)}))
"""


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("file")
    p.add_argument("--old", default="4b6cae5", help="the old side's commit (default 4b6cae5)")
    p.add_argument("--reconstruction", default="tent")
    p.add_argument("--rounds", type=int, default=2)
    args = p.parse_args(argv)
    root = Path(__file__).resolve().parent.parent
    with tempfile.TemporaryDirectory(prefix="mi-amr-ab-") as tmp:
        old = Path(tmp) / "old"
        subprocess.run(["git", "-C", str(root), "worktree", "add", "-q", "--detach", str(old), args.old],
                       check=True)
        try:
            for _ in range(args.rounds):
                for side, path in (("old", old), ("new", root)):
                    env = dict(os.environ, PYTHONPATH=str(path))
                    r = subprocess.run([sys.executable, "-c", ONE, args.file, args.reconstruction],
                                       capture_output=True, text=True, env=env, cwd=tmp)
                    if r.returncode:
                        sys.exit(f"{side}: failed: {r.stderr.strip().splitlines()[-1:]}")
                    rec = json.loads(r.stdout.strip().splitlines()[-1])
                    build = ", ".join(f"{k} {v:.2f}" for k, v in rec["build_s"].items())
                    print(f"{side}: {rec['cells']} cells, {rec['wall_s']:.2f} s wall, {rec['cpu_s']:.2f} s CPU, "
                          f"{rec['cells_per_s'] / 1e6:.2f} M cells/s, B={rec['block']} ({build})", flush=True)
        finally:
            subprocess.run(["git", "-C", str(root), "worktree", "remove", "--force", str(old)], check=False)


if __name__ == "__main__":
    main()
