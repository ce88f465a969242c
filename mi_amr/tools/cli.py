"""The ``mi-amr`` command line: render, reference, frametime, info, convert,
compare, dataset."""

from __future__ import annotations

import argparse
import glob
import json
import os
import sys
import time
from pathlib import Path

from .._llvm import ensure_llvm_path


def _set_variant(variant: str):
    ensure_llvm_path()
    import mitsuba as mi
    if variant not in mi.variants():
        raise SystemExit(f"mi-amr: variant {variant!r} is not available "
                         f"(available: {', '.join(mi.variants())})")
    mi.set_variant(variant)
    import mi_amr  # noqa: F401  (registers the plugins for this variant)
    from ..plugins.medium import require_jit_rgb_variant
    try:
        require_jit_rgb_variant("mi-amr render")
    except RuntimeError as e:
        raise SystemExit(f"mi-amr: {e}")
    return mi


# ---- render ----------------------------------------------------------------
def _scene_from_data(args):
    """``mi-amr render DATA --field NAME``: plan a scene from the data alone
    (`mi_amr.autoscene`), write it as OUT.xml beside the image (yt data are
    converted to OUT.cells first, so that the XML can load them) and return
    its path."""
    from ..autoscene import DEFAULT_TF, field_scalars, plan_scene, write_scene_xml
    from ..data.io import save_cells
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    plan = plan_scene(args.scene, args.field, **_plan_options(args))
    data = Path(args.scene)
    if data.suffix in (".cells", ".npz", ".amrb") and data.is_file():
        data_file = data.resolve()
        if field_scalars(data, args.field) is not None:     # the XML names .cells + scalars: convert to one file
            data_file = save_cells(plan.data.to_cells(), out.with_suffix(".cells")).resolve()
    else:      # a native file: it holds further fields (emission) and reopens at disk speed
        data_file = save_cells(plan.data, out.with_suffix(".amrb" if plan.data.fields else ".cells")).resolve()
    xml = write_scene_xml(plan, data_file, out.with_suffix(".xml"), res=args.res, spp=args.spp)
    if not args.quiet:
        for note in plan.notes:
            print(note)
        print(f"wrote {xml} (edit it and run: mi-amr render {xml} -o {out})")
    return xml


def _plan_options(args) -> dict:
    """`mi_amr.autoscene.plan_scene` options from the data flags."""
    from ..autoscene import DEFAULT_TF, GLOW_TF
    return dict(tf=args.tf or (GLOW_TF if args.emission else DEFAULT_TF), log={"log": True, "linear": False}.get(args.scale),
                value_range=tuple(args.range) if args.range else None,
                emission=args.emission, emission_field=args.emission_field,
                emission_range=tuple(args.emission_range) if args.emission_range else None,
                emission_scale=args.emission_scale)


def _render_series(args):
    """Data outputs named by a pattern (or ``--movie``): one plan for all
    (`mi_amr.series`), a frame per output, numbered EXR/PNG frames and/or a
    movie. Outputs that cannot be read are named and left out; the exit
    status is 1 when any was."""
    import numpy as np

    from .. import series
    from ..images import write_exr, write_png
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    outputs = series.expand_outputs(args.scene)
    folder = out.with_name(f"{out.stem}_outputs")
    say = (lambda *a: None) if args.quiet else print
    extra = (args.emission_field,) if args.emission and args.emission_field else ()
    stored, failed = series.store_outputs(outputs, args.field, folder, extra,
                                          log=lambda m: print(m, file=sys.stderr))
    if not stored:
        raise SystemExit(f"mi-amr: none of the {len(outputs)} outputs could be read")
    plan = series.plan_series(stored, **_plan_options(args))
    for note in plan.notes:
        say(note)
    scenes = series.frame_scenes(plan, stored, folder, args.res, args.spp, args.orbit)
    t0 = time.perf_counter()
    images = _render_all(args, [(str(s), {}) for s in scenes])
    seconds = time.perf_counter() - t0
    images = [np.array(im, dtype=np.float32) for im in images]
    for (src, _), img in zip(stored, images):
        if not np.all(np.isfinite(img)):
            raise SystemExit(f"mi-amr: the frame of {src} contains {int((~np.isfinite(img)).sum())} non-finite values")
    clean = _denoised(images) if args.denoise else None       # the movie shows the denoised frames
    if args.movie:
        movie = series.encode_movie(clean or images, args.movie, args.fps)
        say(f"wrote {movie} ({len(images)} {'denoised ' if clean else ''}frames at {args.fps} fps)")
    if args.frames or not args.movie:
        for k, img in enumerate(images):
            path = out.with_name(f"{out.stem}_{k:03d}{out.suffix}")
            write_exr(path, img)
            write_png(path.with_suffix(".png"), img)
            if clean:
                _write_denoised(path, clean[k])
        say(f"wrote {out.stem}_000{out.suffix} ... {out.stem}_{len(images) - 1:03d}{out.suffix} (+ .png"
            f"{', -denoised' if clean else ''})")
    say(f"{len(images)} frame(s) of {len(outputs)} outputs in {seconds:.2f} s; scenes and data in {folder}")
    series.report_failed(failed)
    return 1 if failed else 0


def _render_all(args, jobs):
    """Render ``(XML scene, -D parameters)`` jobs: on a Dask cluster with
    ``--workers``/``--scheduler`` (frame-parallel), else one after the other
    here. Returns the images."""
    from .. import distributed
    spp = args.spp
    workers = args.workers
    chunk_spp = args.chunk_spp or -(-spp // max(8, 2 * (workers or 1)))
    name = Path(jobs[0][0]).name
    if workers or args.scheduler:
        client = None
        if args.scheduler:
            from dask.distributed import Client
            client = Client(args.scheduler)
        elif workers:
            client = distributed.local_cluster(workers)
        try:
            threads = max(1, (os.cpu_count() or 1) // workers) if workers and not args.scheduler else None
            return distributed.render_frames(jobs, spp, client, chunk_spp, args.seed, progress=not args.quiet,
                                             desc=name, drjit_threads=threads)
        finally:
            cluster = getattr(client, "cluster", None)
            client.close()
            if cluster is not None and not args.scheduler:
                cluster.close()
    return [distributed.render_local(scene, spp, chunk_spp, args.seed, params=p, progress=not args.quiet,
                                     desc=Path(scene).name) for scene, p in jobs]


def cmd_render(args):
    if args.output is None:
        if not args.movie:
            raise ValueError("-o/--output is needed (the .exr to write; with --movie OUT.mp4 it may be left out)")
        args.output = str(Path(args.movie).with_suffix(".exr"))      # frames and scenes beside the movie
    if args.denoise:                          # before any work: is the denoiser there?
        from ..view.engine import denoiser
        if denoiser()[0] is None:
            raise ValueError(f"--denoise: {denoiser()[1]}")
    _set_variant(args.variant)
    import drjit as dr
    import numpy as np

    from ..images import write_exr, write_png
    is_xml = Path(args.scene).suffix.lower() == ".xml"
    data_flags = (args.field or args.tf or args.range or args.scale or args.emission or args.emission_field
                  or args.emission_range or args.emission_scale is not None)
    if is_xml and data_flags:
        raise SystemExit("mi-amr: --field, --tf, --range, --log, --linear and --emission* are for data files, "
                         "not XML scenes (set those in the scene)")
    if is_xml and args.movie:
        raise SystemExit("mi-amr: --movie renders a run's outputs (a data pattern such as 'DD00??/DD00??'), "
                         "not an XML scene; for -D variations use --frames")
    if (args.emission_field or args.emission_range or args.emission_scale is not None) and not args.emission:
        raise SystemExit("mi-amr: --emission-field, --emission-range and --emission-scale need --emission "
                         "(an emission TF such as blackbody)")
    if not is_xml and (args.movie or glob.has_magic(args.scene)):
        return _render_series(args)
    if args.orbit:
        raise SystemExit("mi-amr: --orbit turns the camera over a run's outputs (with --movie or a pattern)")
    if not is_xml:
        args.scene = str(_scene_from_data(args))
    frames, varying = _frames(args)
    spp = args.spp
    t0 = time.perf_counter()
    images = _render_all(args, [(args.scene, p) for p in frames])
    seconds = time.perf_counter() - t0
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    for k, (params, image) in enumerate(zip(frames, images)):
        img = np.array(image, dtype=np.float32)
        if not np.all(np.isfinite(img)):
            raise SystemExit(f"mi-amr: the rendered image contains {int((~np.isfinite(img)).sum())} "
                             "non-finite values")
        path = out if len(frames) == 1 else out.with_name(f"{out.stem}_{k:03d}{out.suffix}")
        write_exr(path, img)
        write_png(path.with_suffix(".png"), img)
        if not args.quiet:
            what = " ".join(f"{a}={b}" for a, b in params.items() if a in varying)
            print(f"wrote {path} and {path.with_suffix('.png')} ({img.shape[1]}x{img.shape[0]}, "
                  f"{spp} spp{', ' + what if what else ''})")
    if args.denoise:
        _denoise_images(args, frames, images)
    if not args.quiet:
        print(f"{len(frames)} frame(s) in {seconds:.2f} s")
    dr.sync_thread()


def _denoise_images(args, frames, images):
    """``--denoise``: OUT-denoised.exr/.png beside each image."""
    out = Path(args.output)
    for k, clean in enumerate(_denoised(images)):
        path = _write_denoised(out if len(frames) == 1 else out.with_name(f"{out.stem}_{k:03d}{out.suffix}"), clean)
        if not args.quiet:
            print(f"wrote {path} and {path.with_suffix('.png')} (denoised)")


def _denoised(images) -> list:
    """The images (linear RGB) through Intel Open Image Denoise."""
    import numpy as np

    from ..view.engine import denoiser
    denoise, missing = denoiser()
    if denoise is None:
        raise ValueError(f"--denoise: {missing}")
    return [denoise(np.asarray(image, dtype=np.float32)[..., :3]) for image in images]


def _write_denoised(path: Path, clean) -> Path:
    """``clean`` as PATH-denoised.exr and .png beside ``path``; the EXR's path."""
    from ..images import write_exr, write_png
    path = path.with_name(f"{path.stem}-denoised{path.suffix}")
    write_exr(path, clean)
    write_png(path.with_suffix(".png"), clean)
    return path


def cmd_view(args):
    import webbrowser

    from ..view.engine import ViewEngine
    from ..view.server import ViewServer, warn_if_exposed
    if Path(args.scene).suffix.lower() == ".xml" and args.field:
        raise ValueError("--field is for data, not XML scenes")
    if not Path(args.scene).exists():
        raise FileNotFoundError(f"{args.scene}: no such file or directory")
    _set_variant(args.variant)
    engine = ViewEngine(args.scene, args.field, res=args.res, max_spp=args.max_spp,
                        preview_scale=args.preview_scale, variant=args.variant)
    server = ViewServer(engine, args.host, args.port, out_dir=args.out)
    warn_if_exposed(args.host)
    engine.start()
    print(f"mi-amr view: {server.url}", flush=True)
    print("(Ctrl-C stops the viewer)", flush=True)
    if not args.no_browser:
        webbrowser.open(server.url)
    try:
        server.run()
    finally:
        engine.stop()


def _frames(args) -> tuple[list[dict], list[str]]:
    """The ``-D`` parameters of each frame, and the names that vary: one
    frame, or with ``--frames`` every combination of the comma-separated
    values (first name slowest)."""
    import itertools
    params = _scene_params(args)
    if not args.frames:
        return [params], []
    lists = {k: v.split(",") for k, v in params.items()}
    varying = [k for k, v in lists.items() if len(v) > 1]
    if not varying:
        raise SystemExit("mi-amr: --frames needs a -D NAME=V1,V2,... with several values")
    return [dict(zip(lists, combo)) for combo in itertools.product(*lists.values())], varying


# ---- reference / frametime -------------------------------------------------
def _scene_params(args):
    params = {}
    for item in getattr(args, "define", None) or []:
        if "=" not in item:
            raise SystemExit(f"mi-amr: -D expects NAME=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        params[k] = v
    return params


def _timed_render(mi, scene, spp, repeats, seed=0):
    """Median wall time of ``repeats`` renders after a warm-up render that
    compiles the kernels; returns (seconds, compile_seconds, image)."""
    import numpy as np
    t0 = time.perf_counter()
    np.array(mi.render(scene, spp=1, seed=seed + 10_000))
    compile_s = time.perf_counter() - t0
    times, img = [], None
    for r in range(repeats):
        t0 = time.perf_counter()
        img = np.array(mi.render(scene, spp=spp, seed=seed + r))
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), compile_s, img


def cmd_reference(args):
    mi = _set_variant(args.variant)
    import tempfile

    import numpy as np

    from ..images import write_exr, write_png
    from .reference import reference_scene
    with tempfile.TemporaryDirectory() as tmp:
        scene, _ = reference_scene(args.scene, tmp, **_scene_params(args))
        img = np.array(mi.render(scene, spp=args.spp, seed=args.seed), dtype=np.float32)
    write_exr(args.output, img)
    write_png(Path(args.output).with_suffix(".png"), img)
    if not args.quiet:
        print(f"wrote {args.output} (heterogeneous + gridvolume reference, {args.spp} spp)")


def cmd_frametime(args):
    mi = _set_variant(args.variant)
    import tempfile

    from ..images import compare_images
    from ..scene_xml import with_amr_parameters
    from .reference import reference_scene
    params = _scene_params(args)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        configs = [("amr majorant=ray", lambda: with_amr_parameters(args.scene, {"majorant": "ray"}, **params)),
                   ("amr majorant=global", lambda: with_amr_parameters(args.scene, {"majorant": "global"}, **params)),
                   ("heterogeneous reference", lambda: reference_scene(args.scene, tmp, **params)[0])]
        images = {}
        for name, load in configs:
            t0 = time.perf_counter()
            scene = load()
            load_s = time.perf_counter() - t0
            sec, comp, img = _timed_render(mi, scene, args.spp, args.repeats, seed=args.seed + 1000 * len(rows))
            images[name] = img
            rows.append({"config": name, "load_s": load_s, "compile_s": comp, "frame_s": sec})
    ref_t = rows[-1]["frame_s"]
    ref_img = images["heterogeneous reference"]
    if not args.quiet:
        print(f"{args.scene}: {args.spp} spp per frame, median of {args.repeats} frames "
              f"(after a warm-up frame that compiles the kernels)")
    print(f"{'configuration':26s} {'load s':>8s} {'compile s':>10s} {'frame s':>9s} "
          f"{'vs reference':>13s} {'mean radiance':>14s}")
    for r in rows:
        r["speedup_vs_reference"] = ref_t / r["frame_s"]
        r["mean"] = float(images[r["config"]].mean())
        print(f"{r['config']:26s} {r['load_s']:8.2f} {r['compile_s']:10.2f} {r['frame_s']:9.3f} "
              f"{r['speedup_vs_reference']:12.2f}x {r['mean']:14.5f}")
    for name in ("amr majorant=ray", "amr majorant=global"):
        if args.quiet:
            break
        st = compare_images(images[name], ref_img)
        print(f"relative RMSE of {name} vs reference at {args.spp} spp (noise of both + bias; "
              f"independent seeds): {st['relative_rmse']:.3%}")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))


# ---- info ------------------------------------------------------------------
def cmd_info(args):
    """Levels, cells, domain, fields (ranges, shares of zeros and negatives)
    and the memory of an ``amr`` medium over the data (`mi_amr.tools.info`);
    with ``--json`` one JSON object on one line."""
    ensure_llvm_path()
    from .info import describe, format_info
    info = describe(args.file, args.field, args.scalars)
    if args.json:
        print(json.dumps(info))
    else:
        print(format_info(info))


# ---- convert ---------------------------------------------------------------
def cmd_convert(args):
    ensure_llvm_path()
    import numpy as np

    from ..data.convert import dense_to_amr
    from ..data.io import load_cells, load_volume, save_cells
    src = Path(args.input)
    if src.suffix in (".cells", ".npz", ".amrb") and Path(args.output).suffix == ".amrb":
        cells = load_volume(src, overlap=args.overlap)      # streamed into blocks, never per-cell records
    elif src.suffix in (".cells", ".npz", ".amrb"):
        cells = load_cells(src, overlap=args.overlap)
    elif src.suffix in (".npy", ".raw"):
        if src.suffix == ".npy":
            vol = np.load(src, allow_pickle=False)
        else:
            if not args.shape:
                raise SystemExit("mi-amr convert: a .raw volume needs --shape X Y Z")
            nx, ny, nz = args.shape
            expected = nx * ny * nz * np.dtype(args.dtype).itemsize
            size = src.stat().st_size
            if size != expected:
                raise SystemExit(f"mi-amr convert: {src} has {size} bytes, but --shape "
                                 f"{nx} {ny} {nz} with {args.dtype} needs {expected}")
            vol = np.fromfile(src, dtype=args.dtype).reshape(nz, ny, nx)
        cells = dense_to_amr(vol, args.threshold, args.max_level, source=str(src))
    elif args.field:
        from ..autoscene import _yt_load
        from ..data.yt_import import from_yt_blocks
        try:
            ds = _yt_load(src)
        except ImportError as e:
            raise SystemExit(f"mi-amr convert: {e}")
        field = tuple(args.field.split(",")) if "," in args.field else args.field
        cells = from_yt_blocks(ds, field, overlap=args.overlap)        # grids straight into blocks
    else:
        raise SystemExit(f"mi-amr convert: unknown input type '{src.suffix}' (expected .cells, "
                         ".npz, .amrb, .npy or .raw, or a yt-loadable dataset with --field)")
    if args.log:
        from ..data.transform import apply_value_transform
        cells, floor = apply_value_transform(cells, "log10")
        print(f"values replaced by log10(max(v, {floor:.6g})): {floor:.6g} is the smallest positive value")
    if Path(args.output).suffix == ".amrb":
        from ..native_file import save_native
        out = save_native(cells, args.output)          # with the grids a medium builds first
    else:
        out = save_cells(cells, args.output)
    print(f"wrote {out}: {cells}")


# ---- compare ---------------------------------------------------------------
def cmd_compare(args):
    import numpy as np

    from ..images import read_exr, write_exr
    from ..images import compare_images
    a, b = read_exr(args.a), read_exr(args.b)
    try:
        stats = compare_images(a, b)
    except ValueError as e:
        raise SystemExit(f"mi-amr compare: {e}")
    if args.diff:
        write_exr(args.diff, np.abs(a - b))
    if args.json:
        print(json.dumps(stats, indent=2))
        return
    print(f"A: {args.a}\nB: {args.b} (reference)")
    print(f"RMSE {stats['rmse']:.6g}   relative RMSE {stats['relative_rmse']:.4%}   "
          f"MAE {stats['mae']:.6g}   max |A-B| {stats['max_abs']:.6g}")
    print(f"mean A {stats['mean_a']:.6g}   mean B {stats['mean_b']:.6g}")
    for name, c in zip("RGBA", stats["channels"]):
        print(f"  {name}: RMSE {c['rmse']:.6g}  mean A {c['mean_a']:.6g}  mean B {c['mean_b']:.6g}  "
              f"max |A-B| {c['max_abs']:.6g}")
    if stats["nonfinite_a"] or stats["nonfinite_b"]:
        print(f"non-finite pixels: A {stats['nonfinite_a']}, B {stats['nonfinite_b']}")
    if args.diff:
        print(f"difference image: {args.diff}")


# ---- dataset ---------------------------------------------------------------
def cmd_dataset(args):
    ensure_llvm_path()
    from ..data.datasets import BLOCK_DATASETS, make_dataset, write_block_dataset
    from ..data.io import save_cells
    if args.name in BLOCK_DATASETS and Path(args.output).suffix == ".cells":
        # streamed block by block: no per-cell array of the whole data set
        from ..progress import progress
        with progress(int(args.cells), f"writing {args.output}") as bar:
            out = write_block_dataset(args.output, int(args.cells), args.levels, args.seed, args.nxb, bar,
                                      name=args.name, layout=args.layout)
        print(f"wrote {out}: {out.stat().st_size // 16} cells in blocks ({args.layout} layout)")
        return
    if args.nxb is not None:
        raise SystemExit("mi-amr dataset: --nxb applies to 'blocks' and 'cosmo' written as .cells")
    if args.layout != "blocks":
        raise SystemExit("mi-amr dataset: --layout applies to 'blocks' and 'cosmo' written as .cells")
    cells = make_dataset(args.name, args.cells, args.levels, args.seed)
    out = save_cells(cells, args.output)
    print(f"wrote {out}: {cells}")


def _count(text: str) -> int:
    """A positive count, written as an integer or in e-notation (1.31e9)."""
    import math
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(v) or v < 1 or v != round(v):
        raise argparse.ArgumentTypeError(f"not a positive whole count: {text!r}")
    return int(round(v))


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


def _render_flags(p, spp: int):
    """The flags every command that renders takes."""
    p.add_argument("--spp", type=int, default=spp, help=f"samples per pixel (default {spp})")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--variant", default="llvm_ad_rgb")
    p.add_argument("-D", "--define", action="append", metavar="NAME=VALUE",
                   help="set a scene <default> parameter, e.g. -D res=512 -D tf=spiky")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar or summary")


def _command(sub, name, help, example, **kw):
    """A subcommand whose --help ends with an example."""
    return sub.add_parser(name, help=help, description=help, epilog=f"example:\n  {example}",
                          formatter_class=argparse.RawDescriptionHelpFormatter, **kw)


def build_parser():
    p = argparse.ArgumentParser(prog="mi-amr", description=__doc__,
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
    r.add_argument("--range", type=float, nargs=2, metavar=("LO", "HI"),
                   help="data: TF domain (in log10 units with --log; default: 1st-99.9th volume percentiles)")
    r.add_argument("--tf", help="data: TF preset (spiky, foggy, ramp, constant) or .json file (default spiky)")
    r.add_argument("--emission", metavar="TF",
                   help="data: make the gas glow with this emission TF (preset blackbody, a matplotlib "
                        "colormap or .json file); the scene then has no other light")
    r.add_argument("--emission-field", metavar="NAME",
                   help="data: the field the emission reads (e.g. temperature; default: --field)")
    r.add_argument("--emission-range", type=float, nargs=2, metavar=("LO", "HI"),
                   help="data: emission TF domain (default: 1st-99.9th volume percentiles, log10 chosen "
                        "as for --field)")
    r.add_argument("--emission-scale", type=float, default=None,
                   help="data: radiance of emission TF colour 1 (default: the mean glow of the gas is 1)")
    r.add_argument("--movie", metavar="OUT.mp4",
                   help="data: render every output the pattern names (e.g. 'DD00??/DD00??') with one TF "
                        "range over all of them, and encode the frames as an H.264 movie (without -o, the "
                        "frames and scenes go beside it: see -o)")
    r.add_argument("--fps", type=int, default=10, help="frames per second of --movie (default 10)")
    r.add_argument("--orbit", type=float, default=0.0, metavar="DEGREES",
                   help="turn the camera by this much about the up axis over a run's outputs (default 0)")
    r.add_argument("--res", type=int, default=400, help="data: image width and height (default 400)")
    r.add_argument("-o", "--output", help="output .exr path; with --movie OUT.mp4 it may be left out: then "
                                          "OUT.exr beside the movie (--frames writes OUT_000.exr, ...; the "
                                          "scenes and data go to OUT_outputs/)")
    r.add_argument("--denoise", action="store_true",
                   help="also write OUT-denoised.exr/.png: Intel Open Image Denoise (mi-amr[view] extra)")
    _render_flags(r, 64)
    r.add_argument("--chunk-spp", type=int, default=None,
                   help="samples per chunk (default: spp / max(8, 2 x workers), rounded up)")
    r.add_argument("--workers", type=int, default=None,
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
                        "from other machines, with the token)")
    v.add_argument("--out", default=".", help="folder for snapshots (default: the current one)")
    v.add_argument("--no-browser", action="store_true", help="print the URL, do not open a browser")
    v.add_argument("--res", type=int, default=256, help="image width (default 256)")
    v.add_argument("--max-spp", type=int, default=1024, help="stop refining at this many spp (default 1024)")
    v.add_argument("--preview-scale", type=float, default=0.5,
                   help="resolution of the first pass after a change, while dragging (default 0.5; 1: off)")
    v.add_argument("--variant", default="llvm_ad_rgb")
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
    t.add_argument("--repeats", type=int, default=3)
    t.add_argument("--json", help="also write the numbers to this file")
    t.set_defaults(func=cmd_frametime)

    i = _command(sub, "info", "summarise AMR data, opened as render opens them: levels, cells per level and "
                 "their sizes, the domain, each field's range with its shares of zeros and negatives, the memory "
                 "of an amr medium over them",
                 "mi-amr info DD0018/DD0018 --field density --json")
    i.add_argument("file", help="a .cells/.npz/.amrb file or anything yt can load")
    i.add_argument("--field", help="the field (yt data: needed; .cells: reads NAME-FIELD.scalars when there)")
    i.add_argument("--scalars", help="a .cells file's scalars file (default NAME.scalars)")
    i.add_argument("--json", action="store_true", help="print the same as one JSON object (one line)")
    i.set_defaults(func=cmd_info)

    c = _command(sub, "convert", "convert between .npz, .cells and .amrb (the native file that opens at "
                                 "disk speed), a dense .npy/.raw volume or a yt-loadable dataset (--field) to AMR",
                 "mi-amr convert volume.raw volume.cells --shape 256 256 256 --threshold 0.01")
    c.add_argument("input")
    c.add_argument("output")
    c.add_argument("--threshold", type=float, default=0.0, help="max value spread of merged blocks")
    c.add_argument("--max-level", type=int, default=4)
    c.add_argument("--shape", type=int, nargs=3, metavar=("X", "Y", "Z"), help="dimensions of a .raw volume")
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
    d.add_argument("--levels", type=int, default=4)
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--layout", default="blocks", choices=("blocks", "zfast", "level", "space", "shuffled"),
                   help="order of the cells in the file, as other writers lay them out: blocks (each block's "
                        "cells together, x fastest), zfast (z fastest inside blocks), level (blocks of one "
                        "physical size, so coarser blocks hold fewer cells, grouped by level), space (blocks "
                        "sorted by position), shuffled (random order)")
    d.add_argument("--nxb", type=_block_sizes, default=None, metavar="N[,N...]",
                   help="cells per block side of 'blocks' (default 16); several (e.g. 8,16,32): mixed sizes")
    d.set_defaults(func=cmd_dataset)
    return p


def main(argv=None):
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["bench"]:                 # hand every remaining option to the benchmark
        from ..bench.__main__ import main as bench_main
        return bench_main(argv[1:])
    args = build_parser().parse_args(argv)
    try:
        code = args.func(args)
    except (ValueError, FileNotFoundError, MemoryError) as e:
        print(f"mi-amr {args.command}: error: {e}", file=sys.stderr)
        return 2
    except RuntimeError as e:
        if "failed to instantiate" not in str(e):     # not a scene that failed to load
            raise
        if _plugin_error(str(e)).rstrip(": ").endswith("KeyboardInterrupt"):   # Ctrl-C inside a plugin
            print(f"mi-amr {args.command}: interrupted", file=sys.stderr)
            return 130
        print(f"mi-amr {args.command}: error: {_plugin_error(str(e))}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:                 # Ctrl-C: writers have removed what they had begun
        print(f"mi-amr {args.command}: interrupted", file=sys.stderr)
        return 130
    return code if isinstance(code, int) else 0


def _plugin_error(message: str) -> str:
    """Mitsuba's "failed to instantiate" message without the plugin's
    traceback: where it happened and the exception it raised."""
    where, _, trace = message.partition("Traceback (most recent call last):")
    lines = [ln for ln in trace.splitlines() if ln.strip()]
    return f"{where.strip()} {lines[-1].strip()}" if lines else where.strip()


if __name__ == "__main__":
    sys.exit(main())
