"""The front-page gallery: ``make gallery`` (``python -m mi_amr.tools.gallery``).

Renders each bundled scene at front-page quality into ``docs/images/NAME.png``
(sRGB PNG, kept under 200 kB) and records what it took in
``docs/images/gallery.json`` (seconds, resolution, spp, machine), which the
manual's gallery page (docs/manual/gallery.md) quotes.

``--beside-yt``: yt's ``create_scene`` default beside our default picture
(before: the ``spiky`` default; after: the planned layers, in ``multi``,
``emission_absorption`` and ``ray_march``) on outputs of three codes written in their own
formats (tests/gallery_outputs.py: an Enzo cosmology, an eight-level AMReX
collapse, Athena++ waves, a RAMSES sheet), each picture's colour layers
(`mi_amr.visibility.colour_layers`) and render time under it, into
``docs/images/beside-yt.jpg`` and ``beside-yt.json``.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import mitsuba as mi
import numpy as np

from .. import autoscene, distributed
from ..images import srgb8, write_png
from ..scene_writer import scene_for
from ..visibility import colour_layers
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


#: ``--beside-yt``: (name, gallery_outputs case, code) of the outputs compared.
BESIDE_YT = (("cosmology", "cosmology", "Enzo"), ("deep collapse", "deep", "AMReX"), ("waves", "waves", "Athena++"),
             ("sheet", "sheet", "RAMSES"))


def _yt_default(path, field, res):
    """yt's ``create_scene`` default picture (sRGB uint8) and its seconds."""
    import matplotlib.image as mpimg
    import yt
    t0 = time.perf_counter()
    ds = yt.load(str(path))
    sc = yt.create_scene(ds, ("gas", field) if ("gas", field) in ds.derived_field_list else field)
    sc.camera.resolution = (res, res)
    with tempfile.TemporaryDirectory() as tmp:
        sc.save(str(Path(tmp) / "yt.png"), render=True)
        img = np.round(mpimg.imread(str(Path(tmp) / "yt.png"))[..., :3] * 255).astype(np.uint8)
    return img, time.perf_counter() - t0


def beside_yt(out: Path, res: int = 160, spp: int = 64, work: Path | None = None) -> dict:
    """The ``--beside-yt`` figure (see the module docstring); returns its record."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    # the codes' formats as the repository's tests write them (a maintainer's tool, run from a checkout)
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))
    gallery_outputs = importlib.import_module("gallery_outputs")
    work = Path(work or tempfile.mkdtemp(prefix="beside-yt-"))
    columns = ("yt create_scene", "ours before (default spiky)", "ours: layers, multi",
               "ours: layers, emission_absorption", "ours: layers, ray_march")
    record, pictures = {}, []
    for name, case, code in BESIDE_YT:
        path, field = gallery_outputs.CASES[case](work / case)
        yt_img, yt_s = _yt_default(path, field, res)
        row = [(yt_img, colour_layers(yt_img).count, yt_s)]
        for tf, mode in (("spiky", "multi"), ("layers", "multi"), ("layers", "emission_absorption"),
                         ("layers", "ray_march")):
            t0 = time.perf_counter()
            old = autoscene.DEFAULT_TF
            autoscene.DEFAULT_TF = tf                  # the default plan with that default TF
            try:
                plan = autoscene.plan_scene(str(path), field)
            finally:
                autoscene.DEFAULT_TF = old
            img = srgb8(np.array(mi.render(mi.load_dict(scene_for(plan, res=res, spp=spp, mode=mode)), spp=spp)))
            row.append((img, colour_layers(img).count, time.perf_counter() - t0))
        record[name] = {"code": code, "case": case, "columns": columns,
                        "layers": [c for _, c, _ in row], "seconds": [round(t, 1) for _, _, t in row]}
        pictures.append((f"{name} ({code})", row))
    fig, axes = plt.subplots(len(pictures), len(columns), figsize=(2.1 * len(columns), 2.35 * len(pictures)))
    for r, (label, row) in enumerate(pictures):
        for c, (img, count, seconds) in enumerate(row):
            ax = axes[r, c]
            ax.imshow(img)
            ax.set_xticks([]), ax.set_yticks([])
            ax.set_xlabel(f"{count} colour layers, {seconds:.1f} s", fontsize=8)
            if r == 0:
                ax.set_title(columns[c].replace(", ", ",\n"), fontsize=8)
            if c == 0:
                ax.set_ylabel(label, fontsize=8)
    fig.tight_layout()
    out.mkdir(parents=True, exist_ok=True)
    fig.savefig(out / "beside-yt.jpg", dpi=80, pil_kwargs={"quality": 85})
    plt.close(fig)
    record["_settings"] = {"res": res, "spp": spp, "machine": f"{os.cpu_count()} cores, {platform.machine()}",
                           "seconds": "plan + render (ours), load + create_scene + render + save (yt)"}
    (out / "beside-yt.json").write_text(json.dumps(record, indent=1) + "\n")
    return record


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
    p.add_argument("--beside-yt", action="store_true", help="the figure of yt's default beside ours (see above)")
    args = p.parse_args(argv)
    _set_variant(args.variant)
    out = Path(args.out)
    if args.beside_yt:
        print(json.dumps(beside_yt(out, min(args.res, 160), min(args.spp, 64)), indent=1))
        return 0
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
