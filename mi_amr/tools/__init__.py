"""Tools a user calls: the command line, mi-amr info, the gallery, dense references (benchmarks: mi_amr.bench)."""
