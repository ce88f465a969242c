"""The closing figure of docs/manual/viewer.md "Annotations" and "Clip plane
and slice": the gallery's ``collapse`` AMReX plotfile (tests/gallery_outputs.py,
three levels refined around the centre) path-traced with its domain outline
and the boxes of its AMR levels drawn by the camera that rendered it, the
medium clipped at z = 0 (the upper half removed), and beside it the slice
through z = 0 of the same field, in the same TF's colours, with the level
boundaries drawn.

    python tools/make_levels_figure.py docs/images/levels-and-slice.png [--res 300 --spp 256]
"""

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("--res", type=int, default=300)
    ap.add_argument("--spp", type=int, default=256)
    args = ap.parse_args()
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import mi_amr
    from mi_amr.transfer.function import TransferFunction
    from gallery_outputs import collapse

    with tempfile.TemporaryDirectory() as tmp:
        path, field = collapse(tmp)
        sc = mi_amr.scene(str(path), field, res=args.res, spp=args.spp, mode="single")
        sc.clip = ((0.0, 0.0, 1.0), 0.0)                   # keep z <= 0: the slice plane's lower side
        t0 = time.perf_counter()
        image = sc.render(seed=0, annotate="outline,levels,legend")
        took = time.perf_counter() - t0
        s = sc.slice("z", 0.0, args.res)
        tf = TransferFunction.load(sc.tf, sc.tf_range)
        ext = sc.placement.phys_extent
        unit = sc.placement.unit
    fig, axes = plt.subplots(1, 2, figsize=(2 * args.res / 100 + 1.2, args.res / 100 + 0.6), dpi=100)
    axes[0].imshow(image.annotated_srgb)
    zc = sc.placement.phys_lo[2] + 0.5 * sc.placement.phys_extent[2]
    axes[0].set_title(f"path traced, single scattering, {args.spp} spp, clipped at z = {zc:.3g};\n"
                      "AMR levels 1 (orange) and 2 (green)", fontsize=8)
    axes[0].axis("off")
    lo = sc.placement.phys_lo
    axes[1].imshow(s.image(tf), extent=(lo[0], lo[0] + ext[0], lo[1], lo[1] + ext[1]), interpolation="nearest")
    axes[1].set_title(f"slice z = {lo[2] + 0.5 * ext[2]:.3g}, {'log10 ' if sc.log else ''}{field} "
                      f"({s.method});\nthe TF's colours, level boundaries drawn", fontsize=8)
    axes[1].set_xlabel(f"x [{unit}]", fontsize=8)
    axes[1].set_ylabel(f"y [{unit}]", fontsize=8)
    axes[1].tick_params(labelsize=7)
    fig.tight_layout()
    fig.canvas.draw()
    from PIL import Image                                  # the docs keep images under 200 kB
    Image.fromarray(np.asarray(fig.canvas.buffer_rgba())[..., :3]).save(args.out, optimize=True)
    levels = {int(k): int((s.refinement == k).sum()) for k in np.unique(s.refinement)}
    print(f"wrote {args.out}: render {took:.1f} s, slice pixels per refinement level {levels}")


if __name__ == "__main__":
    main()
