"""Tools: command line, benchmark, dense references, XML scene rewriting, image I/O."""
