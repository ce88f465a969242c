"""Write a synthetic density field in Enzo's own output format, for the
README's one-command example (no real Enzo output is bundled: they are
hundreds of MB). A log-normal "cosmic web" on a 64^3 root grid, with level-1
grids of 16^3 over its densest regions, and a gas temperature that rises
with density, written by mi_amr.data.enzo_example (notebooks/quickstart.ipynb
writes a smaller one with it).

    python tools/make_enzo_example.py out/enzo     # -> out/enzo/DD0018/DD0018
    mi-amr render out/enzo/DD0018/DD0018 --field density -o out/enzo.exr
"""

import sys

from mi_amr.data.enzo_example import cosmic_web, temperature, write_example  # noqa: F401  (the package writes it)


def main(out):
    path = write_example(out)
    print(f"wrote {path} (+ .hierarchy, .cpu0000): 64^3 root cells, 24 level-1 grids of 16^3, "
          f"fields Density and Temperature")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "out/enzo")
