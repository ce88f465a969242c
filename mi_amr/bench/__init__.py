"""The benchmarks (``python -m mi_amr.bench``, also ``mi-amr bench``).

* `mi_amr.bench.__main__`: the command line (parse, dispatch, run).
* `mi_amr.bench.protocol`: the main benchmark, render time against error.
* `mi_amr.bench.scale`: time to the first picture and memory against the cell count.
* `mi_amr.bench.resample`: the amr medium against dense resamples.
* `mi_amr.bench.peers`: other renderers on the same field (`mi_amr/bench/peer_eradiate.py`).
* `mi_amr.bench.view`: how interactive ``mi-amr view`` is.
* `mi_amr.bench.distributed`: the speed-up of a Dask cluster.
* `mi_amr.bench.harness`: what they share (the scene, frame timing, idle waits).
"""
