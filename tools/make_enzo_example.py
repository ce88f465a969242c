"""Write a synthetic density field in Enzo's own output format, for the
README's one-command example (no real Enzo output is bundled: they are
hundreds of MB). A log-normal "cosmic web" on a 64^3 root grid, with level-1
grids of 16^3 over its densest regions, and a gas temperature that rises
with density, written by tests/amr_formats.py.

    python tools/make_enzo_example.py out/enzo     # -> out/enzo/DD0018/DD0018
    mi-amr render out/enzo/DD0018/DD0018 --field density -o out/enzo.exr
"""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from amr_formats import write_enzo  # noqa: E402


def cosmic_web(n, rng):
    """A log-normal field with a red power spectrum: filaments and knots
    spanning several decades (g/cm^3-like values from about 1e-31)."""
    k = np.fft.fftfreq(n)
    kk = np.sqrt(k[:, None, None] ** 2 + k[None, :, None] ** 2 + k[None, None, :] ** 2)
    amp = np.exp(-(kk * 12) ** 2) * np.where(kk > 0, np.maximum(kk, 1e-9) ** -1.6, 0.0)
    g = np.real(np.fft.ifftn(amp * np.exp(2j * np.pi * rng.random((n, n, n)))))
    g = (g - g.mean()) / g.std()
    return 1e-29 * np.exp(2.3 * g)


def temperature(density):
    """A synthetic gas temperature (K): shock-heated where the gas is dense,
    ``1e4 K (rho / 1e-29)^0.7``, from about 1e3 K in voids to 1e6 K in knots."""
    return 1e4 * (np.asarray(density) / 1e-29) ** 0.7


def main(out):
    rng = np.random.default_rng(18)
    fine = cosmic_web(128, rng)                      # the field at level-1 resolution
    root = fine.reshape(64, 2, 64, 2, 64, 2).mean(axis=(1, 3, 5))
    # refine the 16^3-cell level-1 boxes (8^3 root cells) of highest peak density
    blocks = root.reshape(8, 8, 8, 8, 8, 8).max(axis=(1, 3, 5))
    order = np.argsort(blocks.ravel())[::-1][:24]
    children = []
    for b in order:
        i, j, k = np.unravel_index(b, blocks.shape)
        start = np.array([i, j, k]) * 16
        children.append((start, fine[start[0]:start[0] + 16, start[1]:start[1] + 16, start[2]:start[2] + 16]))
    path = write_enzo(Path(out) / "DD0018", "DD0018", root, children, extra={"Temperature": temperature})
    print(f"wrote {path} (+ .hierarchy, .cpu0000): 64^3 root cells, {len(children)} level-1 grids of 16^3, "
          f"fields Density and Temperature")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "out/enzo")
