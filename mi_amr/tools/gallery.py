"""The front-page gallery: ``make gallery`` (``python -m mi_amr.tools.gallery``).

Renders each bundled scene at front-page quality into ``docs/images/NAME.png``
(sRGB PNG, kept under 200 kB) and records what it took in
``docs/images/gallery.json`` (seconds, resolution, spp, machine), which the
manual's gallery page (docs/manual/gallery.md) quotes.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from .. import distributed
from ..images import write_png
from .render import set_variant as _set_variant

#: name -> (scene, -D parameters, caption)
GALLERY = {
    "cloud": ("scenes/cloud.xml", {"tf": "foggy"},
              "octree-like cloud, foggy TF: multiple scattering lights the inside, soft shadow on the ground"),
    "blocks": ("scenes/blocks.xml", {"tf": "spiky"},
               "block-structured data (FLASH-like 16^3 blocks), spiky TF: thin iso-shells with coloured scattering"),
    "shell": ("scenes/shell.xml", {"tf": "spiky"},
              "a refined spherical shell, spiky TF: a translucent skin and its shadow"),
    "stadium": ("scenes/stadium.xml", {"tf": "spiky"},
                "teapot in a stadium: a finely refined torus, 6% of a coarse domain, seen up close"),
}
MAX_BYTES = 200_000


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m mi_amr.tools.gallery", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="example: python -m mi_amr.tools.gallery --res 320 --spp 256 cloud shell")
    p.add_argument("names", nargs="*", default=list(GALLERY), help="scenes (default: all)")
    p.add_argument("--res", type=int, default=320)
    p.add_argument("--spp", type=int, default=256)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--variant", default="llvm_ad_rgb")
    p.add_argument("--out", default="docs/images")
    p.add_argument("-q", "--quiet", action="store_true")
    args = p.parse_args(argv)
    _set_variant(args.variant)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    record_path = out / "gallery.json"
    records = json.loads(record_path.read_text()) if record_path.is_file() else {}
    for name in args.names:
        scene, params, caption = GALLERY[name]
        params = dict(params, res=str(args.res))
        t0 = time.perf_counter()
        img = np.array(distributed.render_local(scene, args.spp, -(-args.spp // 8), args.seed, params=params,
                                                progress=not args.quiet, desc=name))
        seconds = time.perf_counter() - t0
        path = write_png(out / f"{name}.png", img)
        size = path.stat().st_size
        if size > MAX_BYTES:
            print(f"warning: {path} is {size} bytes (> {MAX_BYTES}); use a smaller --res")
        records[name] = {"scene": scene, "params": params, "spp": args.spp, "seconds": round(seconds, 1),
                         "bytes": size, "caption": caption, "variant": args.variant,
                         "machine": f"{os.cpu_count()} cores, {platform.machine()}, {platform.system()}"}
        if not args.quiet:
            print(f"wrote {path} ({size // 1000} kB, {args.res}x{args.res}, {args.spp} spp, {seconds:.0f} s)")
        record_path.write_text(json.dumps(records, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
