"""The ``mi-amr`` command line: render, reference, frametime, info, convert,
compare, dataset."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys

from ..params import plugin_error
from ..plugins.integrator import MODES
from .render import render
from .commands import compare, convert, dataset, frametime, reference, view
from .info import describe, format_info


# Each subcommand is a call: ``render`` is `mi_amr.tools.render`, ``info``
# `mi_amr.tools.info`, the others `mi_amr.tools.commands`.
def cmd_render(args):
    return render(args)


def cmd_view(args):
    return view(args)


def cmd_reference(args):
    return reference(args)


def cmd_frametime(args):
    return frametime(args)


def cmd_info(args):
    """Levels, cells, domain, fields (ranges, shares of zeros and negatives)
    and the memory of an ``amr`` medium over the data (`mi_amr.tools.info`);
    yt data without ``--field``: code, domain, levels and every field with
    its units, from the index (no value read); with ``--json`` one JSON
    object on one line."""
    info = describe(args.file, args.field, args.scalars, plan=args.plan)
    print(json.dumps(info) if args.json else format_info(info))


def cmd_convert(args):
    return convert(args)


def cmd_compare(args):
    return compare(args)


def cmd_dataset(args):
    return dataset(args)


def _count(text: str) -> int:
    """A positive count, written as an integer or in e-notation (1.31e9)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(v) or v < 1 or v != round(v):
        raise argparse.ArgumentTypeError(f"not a positive whole count: {text!r}")
    return int(round(v))


def _integer_from(least: int):
    """An argparse type: an integer of at least ``least``."""
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if v < least:
            raise argparse.ArgumentTypeError(f"{v}: at least {least}")
        return v
    return parse


#: An integer of at least 1 (``--res``, ``--spp``, ...).
_positive = _integer_from(1)
#: An integer of at least 0 (a level).
_level = _integer_from(0)


def _finite(text: str) -> float:
    """A finite real number."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"{text}: not finite")
    return v


def _above_zero(text: str) -> float:
    """A finite real number above 0."""
    v = _finite(text)
    if v <= 0:
        raise argparse.ArgumentTypeError(f"{text}: must be > 0")
    return v


def _not_negative(text: str) -> float:
    """A finite real number of at least 0."""
    v = _finite(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"{text}: must be >= 0")
    return v



class _Parser(argparse.ArgumentParser):
    """argparse with its errors in one line: ``mi-amr render: error:
    argument --res: -5: at least 1`` (exit status 2; ``--help`` shows the
    usage)."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())}\n")


def check_ranges(args):
    """Refuse ``--range``/``--emission-range`` with LO >= HI as argparse
    refuses a bad value (one line, exit status 2), before any data are read."""
    for flag in ("range", "emission_range"):
        lo_hi = getattr(args, flag, None)
        if lo_hi is not None and not lo_hi[0] < lo_hi[1]:
            _Parser(prog=f"mi-amr {args.command}").error(
                f"argument --{flag.replace('_', '-')}: {lo_hi[0]:g} {lo_hi[1]:g}: LO must be below HI")


def _block_sizes(text: str):
    """``16`` or ``8,16,32``: one block size, or mixed sizes."""
    try:
        sizes = [int(t) for t in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"block sizes must be integers, got {text!r}") from None
    bad = [s for s in sizes if s < 2 or s & (s - 1)]
    if bad:
        raise argparse.ArgumentTypeError(f"block sizes must be powers of two >= 2, got {bad[0]}")
    return sizes[0] if len(sizes) == 1 else tuple(sizes)


#: ``--variant``'s help: the default is the library's (`mi_amr.rendering.default_variant`).
VARIANT_HELP = "the Mitsuba variant (default: cuda_ad_rgb where a CUDA device works, else llvm_ad_rgb)"


def _render_flags(p, spp: int | None):
    """The flags every command that renders takes (``spp`` None: the
    scene's own sample count, else 64)."""
    p.add_argument("--spp", type=_positive, default=spp,
                   help=f"samples per pixel (default {spp})" if spp else
                   "samples per pixel: the most with adaptive sampling, else in every pixel (default: an XML "
                   "scene's own sample_count, else 1024 adaptive, 64 fixed)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--variant", default=None, help=VARIANT_HELP)
    p.add_argument("-D", "--define", action="append", metavar="NAME=VALUE",
                   help="set a scene <default> parameter, e.g. -D res=512 -D tf=spiky")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar or summary")


def _command(sub, name, help, example, **kw):
    """A subcommand whose --help ends with an example."""
    return sub.add_parser(name, help=help, description=help, epilog=f"example:\n  {example}",
                          formatter_class=argparse.RawDescriptionHelpFormatter, **kw)


def build_parser():
    p = _Parser(prog="mi-amr", description=__doc__,
                                epilog="example:\n  mi-amr render scenes/cloud.xml -o out/cloud.exr --spp 64",
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)

    r = _command(sub, "render", "render a Mitsuba XML scene, or AMR data (e.g. mi-amr render "
                 "DD0018/DD0018 --field density -o out/enzo.exr) with a scene made for them "
                 "(camera, light, TF over the values, written beside the image as OUT.xml), "
                 "to EXR (+ PNG preview)",
                 "mi-amr render scenes/cloud.xml -o out/cloud.exr --spp 256 -D tf=spiky --workers 2")
    r.add_argument("scene", help="an XML scene, or data: a .cells/.npz/.amrb file or anything yt can load")
    r.add_argument("--field", help="data: the field to render (e.g. density, or gas,density)")
    scale = r.add_mutually_exclusive_group()
    scale.add_argument("--log", dest="scale", action="store_const", const="log",
                       help="data: TF over log10 of the values (default: chosen from their dynamic range)")
    scale.add_argument("--linear", dest="scale", action="store_const", const="linear",
                       help="data: TF over the values themselves")
    r.add_argument("--range", type=_finite, nargs=2, metavar=("LO", "HI"),
                   help="data: TF domain (in log10 units with --log; default: 1st-99.9th volume percentiles)")
    r.add_argument("--tf", help="data: TF preset (layers, layers:n=N,width=W,colormap=NAME,low=A, spiky, foggy, ramp, "
                   "constant) or .json file (default: layers, planned)")
    r.add_argument("--emission", metavar="TF",
                   help="data: make the gas glow: 'blackbody' is Planck's law at the emission field in kelvin "
                        "(docs/manual/glowing-gas.md), anything else an emission TF (a matplotlib colormap, a "
                        "preset or .json file); the scene then has no other light")
    r.add_argument("--emission-field", metavar="NAME",
                   help="data: the field the emission reads (e.g. temperature; default: --field)")
    r.add_argument("--emission-range", type=_finite, nargs=2, metavar=("LO", "HI"),
                   help="data: emission TF domain (default: 1st-99.9th volume percentiles, log10 chosen "
                        "as for --field)")
    r.add_argument("--emission-scale", type=_above_zero, default=None,
                   help="data: radiance of emission TF colour 1 (default: the mean glow of the gas is 1)")
    r.add_argument("--iso", type=_finite, nargs="+", metavar="V",
                   help="data: isosurfaces at these values of the field (its own units, at most 4), path traced "
                        "inside the gas (docs/manual/isosurfaces.md)")
    r.add_argument("--iso-only", action="store_true",
                   help="data: the isosurfaces alone (the gas off; needs --iso)")
    r.add_argument("--movie", metavar="OUT.mp4",
                   help="data: render every output the pattern names (e.g. 'DD00??/DD00??') with one TF "
                        "range over all of them, and encode the frames as an H.264 movie (without -o, the "
                        "frames and scenes go beside it: see -o)")
    r.add_argument("--fps", type=_positive, default=10, help="frames per second of --movie (default 10)")
    r.add_argument("--orbit", type=_finite, default=0.0, metavar="DEGREES",
                   help="turn the camera by this much about the up axis over a run's outputs (default 0)")
    r.add_argument("--res", type=_positive, default=400, help="data: image width and height (default 400)")
    r.add_argument("-o", "--output", help="output .exr path; with --movie OUT.mp4 it may be left out: then "
                                          "OUT.exr beside the movie (--frames writes OUT_000.exr, ...; the "
                                          "scenes and data go to OUT_outputs/)")
    r.add_argument("--denoise", action=argparse.BooleanOptionalAction, default=None,
                   help="also write OUT-denoised.exr, shown as OUT.png (OUT.exr stays the unbiased estimate): "
                        "Intel Open Image Denoise (mi-amr[view] extra; default: on where installed, except in "
                        "ray_march; a run's frames: off; docs/manual/adaptive.md)")
    _render_flags(r, None)
    r.add_argument("--noise", type=_above_zero, default=None, metavar="REL",
                   help="adaptive sampling: a 16x16 tile stops once its estimated RMS error is below REL times the "
                        "picture's mean (default 0.1 when denoised, else 0.02); the samples each pixel took go to "
                        "OUT-spp.exr")
    r.add_argument("--time", type=_above_zero, default=None, metavar="SECONDS",
                   help="adaptive sampling: stop rendering after about this many seconds")
    r.add_argument("--no-adaptive", dest="adaptive", action="store_false",
                   help="--spp samples in every pixel (default: adaptive sampling up to --spp, default 1024, "
                        "except in ray_march and on a cluster)")
    r.add_argument("--mode", choices=MODES, default=None,
                   help="the amrvolpath integrator's lighting mode: ray_march (the sci-vis ray marcher: "
                        "the TF colour, self-lit, no noise; data: 4 spp unless --spp), emission_absorption "
                        "(the same integral, path traced), single (single scattering) or multi (default: the "
                        "scene's own; data scenes: multi); a data scene's OUT.xml keeps it")
    r.add_argument("--chunk-spp", type=_positive, default=None,
                   help="samples per chunk (default: spp / max(8, 2 x workers), rounded up)")
    r.add_argument("--workers", type=_positive, default=None,
                   help="render on a local Dask cluster of this many processes (mi-amr[distributed])")
    r.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="render on the Dask cluster of this scheduler, e.g. tcp://host:8786")
    r.add_argument("--frames", action="store_true",
                   help="one frame per combination of comma-separated -D values (e.g. -D tf=spiky,foggy), "
                        "or per output of a data pattern, written as OUTPUT_000.exr, ...; rendered "
                        "frame-parallel on a cluster")
    r.set_defaults(func=cmd_render)

    v = _command(sub, "view", "explore data (or an XML scene with an amr medium) in the browser: "
                 "progressive path tracing, mouse camera, TF editor over the histogram, snapshots "
                 "(mi-amr[view] extra)",
                 "mi-amr view DD0018/DD0018 --field density --out snapshots/")
    v.add_argument("scene", help="data (a .cells/.npz/.amrb file or anything yt can load) or an XML scene")
    v.add_argument("--field", help="data: the field to show (e.g. density)")
    v.add_argument("--port", type=int, default=0, help="port (default: a free one)")
    v.add_argument("--host", default="127.0.0.1",
                   help="address to bind (default 127.0.0.1: this machine only; anything else is reachable "
                        "from other machines, with the token, and needs --allow-remote)")
    v.add_argument("--allow-remote", action="store_true",
                   help="allow a --host other machines reach (the traffic is not encrypted)")
    v.add_argument("--out", default=".", help="folder for snapshots (default: the current one)")
    v.add_argument("--embed-data", action="store_true",
                   help="snapshots of data yt loads copy them (once, as .amrb beside the snapshots); by "
                        "default a snapshot's XML names them by path, field and checksum")
    v.add_argument("--no-browser", action="store_true", help="print the URL, do not open a browser")
    v.add_argument("--res", type=_positive, default=256, help="image width (default 256)")
    v.add_argument("--max-spp", type=_positive, default=1024, help="stop refining at this many spp (default 1024)")
    v.add_argument("--preview-scale", type=_above_zero, default=0.5,
                   help="resolution of the passes while the camera or the TF moves (ray-marched, or "
                        "emission_absorption with --no-hybrid) and of the first pass in the page's mode after "
                        "it stops (default 0.5; 1: full size)")
    v.add_argument("--mode", choices=MODES, default=None,
                   help="the lighting mode the page refines in, and starts its selector at (default: the "
                        "scene's amrvolpath mode, multi for data); drags render in ray_march")
    v.add_argument("--no-hybrid", action="store_true",
                   help="drags render 1-spp emission_absorption passes instead of the ray marcher's "
                        "(noise-free) ones; each page can switch it back")
    v.add_argument("--iso", type=_finite, nargs="+", metavar="V",
                   help="start every page with isosurfaces at these values of the field (its own units, at most 4; "
                        "the page's iso control moves them; docs/manual/isosurfaces.md)")
    v.add_argument("--iso-only", action="store_true", help="start with the isosurfaces alone (the gas off; needs --iso)")
    v.add_argument("--variant", default=None, help=VARIANT_HELP)
    v.set_defaults(func=cmd_view)

    f = _command(sub, "reference", "render a scene with every amr medium replaced by "
                                   "heterogeneous + gridvolume (dense resampling)",
                 "mi-amr reference scenes/cloud.xml -o out/cloud-ref.exr --spp 64")
    f.add_argument("scene")
    f.add_argument("-o", "--output", required=True)
    _render_flags(f, 64)
    f.set_defaults(func=cmd_reference)

    t = _command(sub, "frametime", "frame time of a scene with majorant=ray, =global and "
                                   "the heterogeneous reference, as ratios",
                 "mi-amr frametime scenes/cloud.xml --spp 16 --repeats 3 --json out/frametime.json")
    t.add_argument("scene")
    _render_flags(t, 16)
    t.add_argument("--repeats", type=_positive, default=3)
    t.add_argument("--json", help="also write the numbers to this file")
    t.set_defaults(func=cmd_frametime)

    i = _command(sub, "info", "summarise AMR data, opened as render opens them: levels, cells per level and "
                 "their sizes, the domain, each field's range with its shares of zeros and negatives, the memory "
                 "of an amr medium over them; yt data without --field: the levels and fields there are",
                 "mi-amr info DD0018/DD0018 --field density --json")
    i.add_argument("file", help="a .cells/.npz/.amrb file or anything yt can load")
    i.add_argument("--field", help="the field (yt data: without it, the code, domain, levels and every field with "
                                   "its units, read from the index alone; .cells: reads NAME-FIELD.scalars when there)")
    i.add_argument("--scalars", help="a .cells file's scalars file (default NAME.scalars)")
    i.add_argument("--json", action="store_true", help="print the same as one JSON object (one line)")
    i.add_argument("--plan", action="store_true", help="also plan the picture mi-amr render would make (log10 or "
                                                       "linear, TF range, density) and print its check: the share "
                                                       "of the domain's footprint predicted to show the data")
    i.set_defaults(func=cmd_info)

    c = _command(sub, "convert", "convert between .npz, .cells and .amrb (the native file that opens at "
                                 "disk speed), a dense .npy/.raw volume or a yt-loadable dataset (--field) to AMR",
                 "mi-amr convert volume.raw volume.cells --shape 256 256 256 --threshold 0.01")
    c.add_argument("input")
    c.add_argument("output")
    c.add_argument("--threshold", type=_not_negative, default=0.0, help="max value spread of merged blocks")
    c.add_argument("--max-level", type=_level, default=4)
    c.add_argument("--shape", type=_positive, nargs=3, metavar=("X", "Y", "Z"), help="dimensions of a .raw volume")
    c.add_argument("--dtype", default="float32", help="element type of a .raw volume")
    c.add_argument("--overlap", choices=("error", "finest"), default="error")
    c.add_argument("--field", help="field of a yt-loadable dataset, e.g. density or gas,density")
    c.add_argument("--log", action="store_true",
                   help="write log10 of the values (zero and negative ones first raised to the smallest "
                        "positive value)")
    c.set_defaults(func=cmd_convert)

    m = _command(sub, "compare", "error statistics of A.exr against reference B.exr",
                 "mi-amr compare out/cloud.exr out/cloud-ref.exr --diff out/diff.exr")
    m.add_argument("a")
    m.add_argument("b")
    m.add_argument("--diff", help="write |A - B| to this .exr")
    m.add_argument("--json", action="store_true")
    m.set_defaults(func=cmd_compare)

    _command(sub, "bench", "the benchmark (same as python -m mi_amr.bench; its own --help)",
             "mi-amr bench --quick --out out/bench")

    d = _command(sub, "dataset", "generate a synthetic data set",
                 "mi-amr dataset blocks big.cells --cells 100000000 --levels 5")
    d.add_argument("name", choices=("cloud", "shell", "stadium", "blocks", "cosmo", "sparse"),
                   help="octree-like: cloud, shell, stadium; block-structured (FLASH-like nxb^3 blocks): "
                        "blocks, cosmo (a log-normal cosmic web with halos on Enzo-like 8^3 blocks, "
                        "densities spanning decades); one uniform level (the cloud field on a grid of about --cells points): sparse")
    d.add_argument("output")
    d.add_argument("--cells", type=_count, default=20000, help="about this many cells (1e8 and 1.31e9 are taken)")
    d.add_argument("--levels", type=_positive, default=4)
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--layout", default="blocks", choices=("blocks", "zfast", "level", "space", "shuffled"),
                   help="order of the cells in the file, as other writers lay them out: blocks (each block's "
                        "cells together, x fastest), zfast (z fastest inside blocks), level (blocks of one "
                        "physical size, so coarser blocks hold fewer cells, grouped by level), space (blocks "
                        "sorted by position), shuffled (random order)")
    d.add_argument("--nxb", type=_block_sizes, default=None, metavar="N[,N...]",
                   help="cells per block side of 'blocks' (default 16); several (e.g. 8,16,32): mixed sizes")
    d.set_defaults(func=cmd_dataset)
    for name, command in sub.choices.items():
        if name != "bench":
            command.add_argument("--traceback", action="store_true",
                                 help=f"show the full traceback of an error (also: {TRACEBACK_ENV}=1)")
    return p


#: Set to 1, it shows the full traceback of an error, as ``--traceback`` does.
TRACEBACK_ENV = "MI_AMR_TRACEBACK"

#: What bad input raises (our ValueErrors and ParameterError, a reader's
#: OSError, a missing file, no memory for the data): one line, exit status
#: 2. Anything else is a bug and keeps its traceback.
EXPECTED_ERRORS = (ValueError, OSError, MemoryError)


def one_line(e: BaseException) -> str:
    """An exception's message on one line (its type when it has none)."""
    return " ".join(str(e).split()) or type(e).__name__


def main(argv=None):
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["bench"]:                 # hand every remaining option to the benchmark
        from ..bench.__main__ import main as bench_main
        return bench_main(argv[1:])
    args = build_parser().parse_args(argv)
    check_ranges(args)
    traceback = args.traceback or os.environ.get(TRACEBACK_ENV, "") not in ("", "0")
    try:
        code = args.func(args)
    except EXPECTED_ERRORS as e:
        if traceback:
            raise
        print(f"mi-amr {args.command}: error: {one_line(e)}", file=sys.stderr)
        return 2
    except RuntimeError as e:
        if "failed to instantiate" not in str(e) or traceback:     # not a scene that failed to load
            raise
        if plugin_error(str(e)).rstrip(": ").endswith("KeyboardInterrupt"):   # Ctrl-C inside a plugin
            print(f"mi-amr {args.command}: interrupted", file=sys.stderr)
            return 130
        print(f"mi-amr {args.command}: error: {plugin_error(str(e))}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:                 # Ctrl-C: writers have removed what they had begun
        print(f"mi-amr {args.command}: interrupted", file=sys.stderr)
        return 130
    return code if isinstance(code, int) else 0


if __name__ == "__main__":
    sys.exit(main())
