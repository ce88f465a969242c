"""The bodies of the ``mi-amr`` subcommands other than ``render`` (which
is `mi_amr.tools.render`) and ``info`` (`mi_amr.tools.info`): view, reference,
frametime, convert, compare, dataset. Each takes the parsed arguments of its
subcommand (`mi_amr.tools.cli`)."""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
import time
import webbrowser
from pathlib import Path

import numpy as np

from ..data.opening import is_native, open_dataset, yt_field
from ..data.convert import dense_to_amr
from ..data.datasets import BLOCK_DATASETS, make_dataset, write_block_dataset
from ..data.io import load_cells, load_volume
from ..native_file import save_data
from ..data.transform import apply_value_transform
from ..data.yt_import import from_yt_blocks
from ..images import compare_images, read_exr, write_exr
from ..progress import progress
from .render import scene_params, set_variant, write_frame
from ..scene_xml import integrator_elements, parse_scene, with_amr_parameters
from ..reference import reference_scene


#: After a failed load, how long ``mi-amr view`` waits for a page to show the
#: error before it exits (seconds), and how long a page that got it is given to draw it.
LOAD_ERROR_WAIT = 10.0
LOAD_ERROR_SHOWN = 1.0


def view(args):
    """``mi-amr view``: check every argument (one line each), listen, print
    the URL, open the browser through a private redirect file, serve until
    Ctrl-C. A failed load is printed as one line and shown in the page;
    then the exit status is 2."""
    from ..view.engine import ViewEngine       # lazy: start-up time (Mitsuba, the viewer)
    from ..view.server import ViewServer, is_loopback, redirect_file
    scene, host, port = Path(args.scene), args.host, args.port
    if not scene.exists():
        raise FileNotFoundError(f"{args.scene}: no such file or directory")
    if scene.suffix.lower() == ".xml" and args.field:
        raise ValueError("--field is for data, not XML scenes")
    if scene.suffix.lower() == ".xml" and args.mode is not None:
        root = parse_scene(scene).getroot()
        if not integrator_elements(root):
            kinds = ", ".join(sorted({str(e.get("type")) for e in root.iter("integrator")})) or "none"
            raise ValueError(f"--mode {args.mode}: the scene's integrator is {kinds}: lighting modes need amrvolpath")
    if not 0 <= port <= 65535:
        raise ValueError(f"--port {port}: a port is 0 (any free one) to 65535")
    if not host or not (is_loopback(host) or args.allow_remote):
        raise ValueError(f"--host {host!r} serves other machines: add --allow-remote (the traffic is not encrypted)")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out}: not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ValueError(f"--out {out}: cannot make the folder ({e.strerror or e})") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise ValueError(f"--out {out}: not writable")
    try:
        mi = set_variant(args.variant)
    except SystemExit as e:
        raise ValueError(str(e.code).removeprefix("mi-amr: ")) from None
    engine = ViewEngine(args.scene, args.field, res=args.res, max_spp=args.max_spp,
                        preview_scale=args.preview_scale, variant=mi.variant(), mode=args.mode,
                        embed_data=args.embed_data, hybrid=not args.no_hybrid, iso=args.iso, iso_only=args.iso_only)
    try:
        server = ViewServer(engine, host, port, out_dir=out)
    except (OSError, OverflowError) as e:
        raise ValueError(f"cannot serve on {host}:{port}: {getattr(e, 'strerror', None) or e}") from None
    if not is_loopback(host):
        print(f"mi-amr view: warning: serving {host} for other machines; the traffic (token, data, images) "
              "is not encrypted", file=sys.stderr)
    engine.start()
    server.start()
    print(f"mi-amr view: {server.url}", flush=True)
    print(f"(snapshots go to {server.out_dir}; Ctrl-C stops the viewer)", flush=True)
    opened = None
    try:
        if not args.no_browser:
            opened = redirect_file(server.url)
            webbrowser.open(opened.as_uri())
        while not engine.ready.wait(0.2):
            pass
        if engine.error:
            print(f"mi-amr view: error: {engine.error}", file=sys.stderr, flush=True)
            if server.error_shown.wait(LOAD_ERROR_WAIT):
                time.sleep(LOAD_ERROR_SHOWN)
            return 2
        while server.running():
            time.sleep(0.2)
    except KeyboardInterrupt:
        print("mi-amr view: stopped", file=sys.stderr)
    finally:
        server.stop()
        engine.stop()
        if opened is not None:
            shutil.rmtree(opened.parent, ignore_errors=True)


def timed_render(mi, scene, spp, repeats, seed=0):
    """Median wall time of ``repeats`` renders after a warm-up render that
    compiles the kernels; returns (seconds, compile_seconds, image)."""
    t0 = time.perf_counter()
    np.array(mi.render(scene, spp=1, seed=seed + 10_000))
    compile_s = time.perf_counter() - t0
    times, img = [], None
    for r in range(repeats):
        t0 = time.perf_counter()
        img = np.array(mi.render(scene, spp=spp, seed=seed + r))
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), compile_s, img


def reference(args):
    mi = set_variant(args.variant)
    with tempfile.TemporaryDirectory() as tmp:
        scene, _ = reference_scene(args.scene, tmp, **scene_params(args.define))
        write_frame(args.output, mi.render(scene, spp=args.spp, seed=args.seed))
    if not args.quiet:
        print(f"wrote {args.output} (heterogeneous + gridvolume reference, {args.spp} spp)")


def frametime(args):
    mi = set_variant(args.variant)
    params = scene_params(args.define)
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
            sec, comp, img = timed_render(mi, scene, args.spp, args.repeats, seed=args.seed + 1000 * len(rows))
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


def convert(args):
    src = Path(args.input)
    if is_native(src) and Path(args.output).suffix == ".amrb":
        cells = load_volume(src, overlap=args.overlap)      # streamed into blocks, never per-cell records
    elif is_native(src):
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
        try:
            ds = open_dataset(src, must_exist=False)      # yt names what it cannot find
        except ImportError as e:
            raise SystemExit(f"mi-amr convert: {e}")
        field = yt_field(args.field)
        cells = from_yt_blocks(ds, field, overlap=args.overlap)        # grids straight into blocks
    else:
        raise SystemExit(f"mi-amr convert: unknown input type '{src.suffix}' (expected .cells, "
                         ".npz, .amrb, .npy or .raw, or a yt-loadable dataset with --field)")
    if args.log:
        cells, floor = apply_value_transform(cells, "log10")
        print(f"values replaced by log10(max(v, {floor:.6g})): {floor:.6g} is the smallest positive value")
    out = save_data(cells, args.output)     # .amrb: with the grids a medium builds first
    print(f"wrote {out}: {cells}")


def compare(args):
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


def dataset(args):
    if args.name in BLOCK_DATASETS and Path(args.output).suffix == ".cells":
        # streamed block by block: no per-cell array of the whole data set
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
    out = save_data(cells, args.output)
    print(f"wrote {out}: {cells}")
