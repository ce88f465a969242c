"""Data and I/O: AMR cells, file formats, conversion, synthetic data sets, yt import."""
