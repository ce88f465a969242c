"""Speed-up of sample-parallel rendering on a Dask LocalCluster.

    python -m mi_amr.bench --distributed --workers 2 --out DIR

Renders one scene (default ``scenes/demo.xml`` at 256x256, 256 spp) in this
process (`render_local`, Dr.Jit on every core) and on a LocalCluster of
``workers`` processes with one Dr.Jit thread each (`render`), alternating,
``repeats`` times each. The first round of each includes loading the scene
and compiling the kernels (what one command costs); later rounds reuse the
cluster but load the scene anew. Dask's task stream gives the time the
workers spent inside chunks, so the rest of ``workers x wall`` is scheduling,
transfer and idle time. Writes ``distributed.json`` and ``distributed.md``.
"""

from __future__ import annotations

import json
import statistics
import time
from pathlib import Path

import mitsuba as mi

from .. import distributed as D


def run_distributed(scene: str, workers: int, res: int, spp: int, chunk_spp: int, repeats: int, out: Path):
    params = {"res": str(res)}
    client = D.local_cluster(workers)
    rows = []
    try:
        for r in range(repeats):
            t0 = time.perf_counter()
            D.render_local(scene, spp, chunk_spp, seed=r, params=params)
            local = time.perf_counter() - t0
            from dask.distributed import get_task_stream
            with get_task_stream(client) as ts:
                t0 = time.perf_counter()
                D.render_frames([(scene, params)], spp, client, chunk_spp, seed=r, drjit_threads=1)
                dist = time.perf_counter() - t0
            busy = sum(s["stop"] - s["start"] for t in ts.data for s in t["startstops"]
                       if s["action"] == "compute")
            rows.append({"round": r, "local_s": local, "distributed_s": dist, "speedup": local / dist,
                         "chunks": len(D.chunk_plan(spp, chunk_spp)),
                         "not_in_chunks": 1 - busy / (workers * dist)})
            print(f"round {r}: one process {local:.2f} s, {workers} workers {dist:.2f} s "
                  f"(x{local / dist:.2f}; {rows[-1]['not_in_chunks']:.1%} of worker time outside chunks)",
                  flush=True)
    finally:
        cluster = client.cluster
        client.close()
        cluster.close()
    out.mkdir(parents=True, exist_ok=True)
    summary = {"scene": scene, "workers": workers, "res": res, "spp": spp, "chunk_spp": chunk_spp, "rows": rows}
    (out / "distributed.json").write_text(json.dumps(summary, indent=1))
    warm = rows[1:] or rows
    lines = [f"# Distributed rendering: {workers} workers vs one process",
             "", f"`{scene}`, {res}x{res}, {spp} spp, chunks of {chunk_spp} spp "
             f"({rows[0]['chunks']} chunks), LocalCluster of {workers} processes x 1 Dr.Jit thread "
             "against one process with Dr.Jit on every core.", "",
             "| round | one process s | distributed s | speed-up | worker time outside chunks |",
             "|---|---|---|---|---|"]
    lines += [f"| {x['round']}{' (cold)' if x['round'] == 0 else ''} | {x['local_s']:.2f} | "
              f"{x['distributed_s']:.2f} | {x['speedup']:.2f}x | {x['not_in_chunks']:.1%} |" for x in rows]
    sp = [x["speedup"] for x in warm]
    lines += ["", f"Speed-up over the warm rounds: median {statistics.median(sp):.2f}x "
              f"(range {min(sp):.2f}-{max(sp):.2f})."]
    (out / "distributed.md").write_text("\n".join(lines) + "\n")
    return summary


def main_args(args) -> int:
    """Entry from `mi_amr.bench.__main__` (``--distributed``): 256 spp
    unless ``--spp`` is given."""
    mi.set_variant(args.variant)
    spp = 256 if args.spp == 16 else args.spp
    run_distributed(args.dist_scene, args.workers, args.res, spp, args.chunk_spp, args.repeats, Path(args.out))
    print(f"wrote {args.out}/distributed.json and distributed.md")
    return 0
