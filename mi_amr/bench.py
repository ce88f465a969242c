"""``python -m mi_amr.bench``: the benchmark (see `mi_amr.tools.bench`)."""

from .tools.bench import main

if __name__ == "__main__":
    main()
