"""What ``mi-amr render`` does with its parsed command line: render jobs
and the frames they write. The command line's adapter of the library
(`mi_amr.rendering`: `RenderJob`, `render_jobs`), which a Python user calls
instead.

Three jobs (`render`): an XML scene (with ``-D`` variations as frames), data
planned into a scene (`mi_amr.autoscene`: the planned data are rendered as
they lie in memory, and the XML written beside the image for the user names
a file written once, never loaded again here), and a run's outputs as
frames and a movie (`mi_amr.series`). Every image goes out through
`write_frame` (finite check, EXR + PNG preview), the denoised copies too
(`denoised_path`). ``args`` is the parsed command line of ``mi-amr render``
(`mi_amr.tools.cli`).

By default a picture is rendered adaptively (`mi_amr.adaptive`: up to
``--spp``, tiles stopping at ``--noise``; OUT-spp.exr the samples each
pixel took) and denoised (`mi_amr.denoising`): OUT.exr is the unbiased
estimate, OUT-denoised.exr its denoised copy, OUT.png shows the denoised
one and OUT-raw.png the estimate (docs/manual/adaptive.md).
"""

from __future__ import annotations

import glob
import itertools
import os
import sys
import time
from pathlib import Path

import numpy as np

import drjit as dr
import mitsuba as mi

from .. import distributed, series
from ..autoscene import GLOW_TF, plan_scene
from ..scene_writer import write_scene_xml
from ..data.opening import field_scalars, is_native
from ..native_file import save_data
from ..images import write_exr, write_png
from ..rendering import RenderJob, default_spp, render_jobs, scene_spp, use_variant
from ..adaptive import DEFAULT_MAX_SPP, DEFAULT_NOISE, DENOISED_NOISE
from ..denoising import denoiser_missing

DATA_FLAGS_MESSAGE = ("mi-amr: --field, --tf, --range, --log, --linear, --emission* and --iso* are for data files, "
                      "not XML scenes (set those in the scene)")


def set_variant(variant: str | None):
    """Select the Mitsuba variant ``--variant`` names, or (None) the one the
    library chooses (`mi_amr.rendering.use_variant`: the one set, else
    ``cuda_ad_rgb`` where a CUDA device works, else ``llvm_ad_rgb``), with
    the mi-amr plugins registered; a one-line exit when it is missing or
    refused. Returns ``mitsuba``."""
    try:
        use_variant(variant, say=False)
    except (ValueError, OSError) as e:
        raise SystemExit(f"mi-amr: {e}")
    return mi


# ---- frames ----------------------------------------------------------------
def check_finite(image, what: str = "the rendered image") -> np.ndarray:
    """``image`` as float32, or a one-line exit naming its non-finite values."""
    img = np.array(image, dtype=np.float32)
    if not np.all(np.isfinite(img)):
        raise SystemExit(f"mi-amr: {what} contains {int((~np.isfinite(img)).sum())} non-finite values")
    return img


def write_frame(path, image, what: str = "the rendered image") -> np.ndarray:
    """The one writer of rendered images: ``image`` checked finite, as
    ``path`` (EXR) and its PNG preview beside it; returns the float32 image."""
    img = check_finite(image, what)
    path = Path(path)
    write_exr(path, img)
    write_png(path.with_suffix(".png"), img)
    return img


def denoised_path(path, what: str = "denoised") -> Path:
    """``OUT-denoised.exr`` (or ``OUT-WHAT.exr``) beside ``OUT.exr``."""
    path = Path(path)
    return path.with_name(f"{path.stem}-{what}{path.suffix}")


def frame_path(out, k: int, n: int) -> Path:
    """``OUT`` for a single frame, else ``OUT_000``, ``OUT_001``, ..."""
    out = Path(out)
    return out if n == 1 else out.with_name(f"{out.stem}_{k:03d}{out.suffix}")


def require_denoiser():
    """``--denoise``: fail before any work when the denoiser is missing."""
    from ..view.engine import denoiser
    if denoiser()[0] is None:
        raise ValueError(f"--denoise: {denoiser()[1]}")


def denoised(images) -> list:
    """The images (linear RGB) through Intel Open Image Denoise."""
    from ..view.engine import denoiser
    denoise, missing = denoiser()
    if denoise is None:
        raise ValueError(f"--denoise: {missing}")
    return [denoise(np.asarray(image, dtype=np.float32)[..., :3]) for image in images]


# ---- rendering -------------------------------------------------------------
def scene_params(defines) -> dict:
    """``-D NAME=VALUE`` items as a dict."""
    params = {}
    for item in defines or []:
        if "=" not in item:
            raise SystemExit(f"mi-amr: -D expects NAME=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        params[k] = v
    return params


def frames(args) -> tuple[list[dict], list[str]]:
    """The ``-D`` parameters of each frame, and the names that vary: one
    frame, or with ``--frames`` every combination of the comma-separated
    values (first name slowest)."""
    params = scene_params(args.define)
    if not args.frames:
        return [params], []
    lists = {k: v.split(",") for k, v in params.items()}
    varying = [k for k, v in lists.items() if len(v) > 1]
    if not varying:
        raise SystemExit("mi-amr: --frames needs a -D NAME=V1,V2,... with several values")
    return [dict(zip(lists, combo)) for combo in itertools.product(*lists.values())], varying


def cli_jobs(args, scenes) -> list:
    """`RenderJob`s of the command line: ``scenes`` are ``(XML path,
    -D values)`` or ``(ScenePlan, -D values)``, with ``--spp``, ``--seed``,
    ``--mode``, ``--res`` and the adaptive ``--noise`` and ``--time`` from
    ``args`` (`sampling`)."""
    mode = getattr(args, "mode", None)
    noise = getattr(args, "noise", None)
    return [RenderJob(scene, spp=args.spp, seed=args.seed, mode=mode, res=args.res, defines=dict(p),
                      noise=noise, seconds=getattr(args, "time", None) if noise else None,
                      denoise=bool(getattr(args, "denoise", False)) and getattr(args, "denoise_here", True))
            for scene, p in scenes]


def sampling(args, is_xml: bool):
    """Settle the sampling flags of ``mi-amr render`` in ``args``:
    adaptive (``args.noise`` set) unless ``--no-adaptive``, on a cluster
    (said on stderr), or in ``ray_march`` without ``--noise``, at
    `DENOISED_NOISE` when denoised, else `DEFAULT_NOISE`; ``args.spp``
    the cap or the fixed count (default: an XML scene's own count, else
    `DEFAULT_MAX_SPP` or `default_spp`); ``args.denoise`` on by default where the
    denoiser is installed (said when it is not), off in ``ray_march``."""
    cluster = bool(args.workers or args.scheduler)
    asked = args.noise is not None or args.time is not None
    if not args.adaptive and asked:
        raise ValueError("--noise and --time are for adaptive sampling (leave out --no-adaptive)")
    adaptive = args.adaptive and (args.mode != "ray_march" or asked)
    if adaptive and cluster:
        if asked:
            raise ValueError("--noise and --time render in this process, not on a cluster "
                             "(--workers/--scheduler render --spp samples in every pixel)")
        adaptive = False
        print("mi-amr: on a cluster every pixel gets --spp samples (adaptive sampling runs in one process)",
              file=sys.stderr)
    if args.denoise is None:
        missing = denoiser_missing()
        args.denoise = args.mode != "ray_march" and missing is None
        if missing and args.mode != "ray_march" and not args.quiet:
            print(f"mi-amr: not denoised ({missing})", file=sys.stderr)
    own = scene_spp(args.scene, frames(args)[0][0]) if is_xml else None   # an XML scene's own count
    if adaptive:
        args.noise = args.noise or (DENOISED_NOISE if args.denoise else DEFAULT_NOISE)
        args.spp = args.spp or own or DEFAULT_MAX_SPP
    else:
        args.noise = None
        args.spp = args.spp or own or default_spp(args.mode)      # as Mitsuba would take it


def render_cli_jobs(args, jobs, desc: str | None = None) -> list:
    """Render `RenderJob`s for the command line (`mi_amr.rendering.render_jobs`):
    on a Dask cluster with ``--workers``/``--scheduler`` (frame-parallel),
    else one after the other here, in chunks of ``--chunk-spp``. Returns
    their `mi_amr.rendering.RenderResult`s."""
    spp, workers = args.spp, args.workers
    chunk_spp = args.chunk_spp or -(-spp // max(8, 2 * (workers or 1)))
    options = dict(chunk_spp=chunk_spp, progress=not args.quiet, desc=desc)
    if not (workers or args.scheduler):
        return render_jobs(jobs, **options)
    if args.scheduler:
        from dask.distributed import Client
        client = Client(args.scheduler)
    else:
        client = distributed.local_cluster(workers)
    try:
        threads = max(1, (os.cpu_count() or 1) // workers) if workers and not args.scheduler else None
        return render_jobs(jobs, client, drjit_threads=threads, **options)
    finally:
        cluster = getattr(client, "cluster", None)
        client.close()
        if cluster is not None and not args.scheduler:
            cluster.close()


# ---- data planned into a scene --------------------------------------------
def plan_options(args) -> dict:
    """`mi_amr.autoscene.plan_scene` options from the data flags."""
    return dict(tf=args.tf or (GLOW_TF if args.emission else None),      # None: the default, which the check may change
                log={"log": True, "linear": False}.get(args.scale),
                value_range=tuple(args.range) if args.range else None,
                emission=args.emission, emission_field=args.emission_field,
                emission_range=tuple(args.emission_range) if args.emission_range else None,
                emission_scale=args.emission_scale, iso=getattr(args, "iso", None),
                iso_only=getattr(args, "iso_only", False))


def plan_data(args):
    """``mi-amr render DATA --field NAME``: plan a scene from the data, read
    once (`mi_amr.autoscene.plan_scene`), and write it as OUT.xml beside the
    image for the user. The XML names the data file itself, or (yt data, a
    field's own .scalars) the planned data written once as OUT.amrb/.cells.
    Returns ``(plan, xml path)``."""
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    plan = plan_scene(args.scene, args.field, **plan_options(args))
    data = Path(args.scene)
    if is_native(data) and data.is_file():
        data_file = data.resolve()
        if field_scalars(data, args.field) is not None:     # the XML names .cells + scalars: convert to one file
            data_file = save_data(plan.data.to_cells(), out.with_suffix(".cells")).resolve()
    else:      # a native file: it holds further fields (emission) and reopens at disk speed
        data_file = save_data(plan.data, out.with_suffix(".amrb" if plan.data.fields else ".cells")).resolve()
    xml = write_scene_xml(plan, data_file, out.with_suffix(".xml"), res=args.res, spp=args.spp,
                          mode=getattr(args, "mode", None))
    if not args.quiet:
        for note in plan.notes:
            print(note)
        print(f"wrote {xml} (edit it and run: mi-amr render {xml} -o {out})")
    return plan, xml


def data_jobs(args, plan, xml, frame_params) -> list:
    """The jobs of planned data: here, the plan over the data in memory
    (``-D res`` and ``spp`` apply to it as to the XML); on a cluster, or for
    other ``-D`` names, the XML (workers load its file)."""
    if args.workers or args.scheduler or any(set(p) - {"res", "spp"} for p in frame_params):
        return cli_jobs(args, [(str(xml), p) for p in frame_params])
    return cli_jobs(args, [(plan, p) for p in frame_params])


# ---- the jobs --------------------------------------------------------------
def render(args):
    """``mi-amr render``: an XML scene, data planned into a scene, or a run's
    outputs (`render_series`); returns the exit status (None: 0)."""
    if args.output is None:
        if not args.movie:
            raise ValueError("-o/--output is needed (the .exr to write; with --movie OUT.mp4 it may be left out)")
        args.output = str(Path(args.movie).with_suffix(".exr"))      # frames and scenes beside the movie
    if args.denoise:                          # before any work: is the denoiser there?
        require_denoiser()
    set_variant(args.variant)
    is_xml = Path(args.scene).suffix.lower() == ".xml"
    data_flags = (args.field or args.tf or args.range or args.scale or args.emission or args.emission_field
                  or args.emission_range or args.emission_scale is not None or args.iso or args.iso_only)
    if is_xml and data_flags:
        raise SystemExit(DATA_FLAGS_MESSAGE)
    series_run = not is_xml and (args.movie or glob.has_magic(args.scene))
    if series_run:                            # a run's frames: fixed spp, --denoise when asked (as before)
        args.adaptive = args.adaptive and (args.noise is not None or args.time is not None)
        args.denoise_here = False
        args.denoise = bool(args.denoise)
    sampling(args, is_xml)
    if args.spp < 1:
        raise ValueError(f"--spp {args.spp}: at least 1")
    if is_xml and args.movie:
        raise SystemExit("mi-amr: --movie renders a run's outputs (a data pattern such as 'DD00??/DD00??'), "
                         "not an XML scene; for -D variations use --frames")
    if (args.emission_field or args.emission_range or args.emission_scale is not None) and not args.emission:
        raise SystemExit("mi-amr: --emission-field, --emission-range and --emission-scale need --emission "
                         "(an emission TF such as blackbody)")
    if not is_xml and (args.movie or glob.has_magic(args.scene)):
        return render_series(args)
    if args.orbit:
        raise SystemExit("mi-amr: --orbit turns the camera over a run's outputs (with --movie or a pattern)")
    params, varying = None, None
    if is_xml:
        params, varying = frames(args)
        jobs, desc = cli_jobs(args, [(args.scene, p) for p in params]), None
    else:
        plan, xml = plan_data(args)
        params, varying = frames(args)
        jobs, desc = data_jobs(args, plan, xml, params), Path(xml).name
    t0 = time.perf_counter()
    results = render_cli_jobs(args, jobs, desc)
    seconds = time.perf_counter() - t0
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    for k, (p, result) in enumerate(zip(params, results)):
        path = frame_path(out, k, len(params))
        written = write_result(path, result)
        if not args.quiet:
            what = " ".join(f"{a}={b}" for a, b in p.items() if a in varying)
            samples = result.adaptive.summary() if result.adaptive is not None else f"{args.spp} spp"
            print(f"wrote {', '.join(str(w) for w in written)} ({result.image.shape[1]}x{result.image.shape[0]}"
                  f"{', ' + what if what else ''})\n  {samples}"
                  + (f"\n  {path.with_suffix('.png')} is denoised, {path} the unbiased estimate "
                     "(docs/manual/adaptive.md)"
                     if result.denoised is not None else ""))
    if not args.quiet:
        print(f"{len(params)} frame(s) in {seconds:.2f} s")
    dr.sync_thread()


def write_result(path, result) -> list:
    """Write a `mi_amr.rendering.RenderResult` as ``path`` (the estimate,
    EXR) and its PNG preview, with ``-spp.exr`` (samples per pixel) when
    adaptive, and when denoised ``-denoised.exr``, the PNG then showing the
    denoised picture and ``-raw.png`` the estimate. Returns the paths
    written."""
    path = Path(path)
    img = write_frame(path, result.image)
    written = [path]
    if result.adaptive is not None:
        write_exr(denoised_path(path, "spp"), result.adaptive.spp[..., None])
        written.append(denoised_path(path, "spp"))
    if result.denoised is not None:
        clean = write_frame(denoised_path(path), result.denoised, "the denoised image")
        denoised_path(path).with_suffix(".png").unlink(missing_ok=True)     # OUT.png shows it
        write_png(denoised_path(path.with_suffix(".png"), "raw"), img)
        write_png(path.with_suffix(".png"), clean)
        written += [denoised_path(path), path.with_suffix(".png"), denoised_path(path.with_suffix(".png"), "raw")]
    else:
        written.append(path.with_suffix(".png"))
    return written


def render_series(args):
    """Data outputs named by a pattern (or ``--movie``): one plan for all
    (`mi_amr.series`), a frame per output, numbered EXR/PNG frames and/or a
    movie. Outputs that cannot be read are named and left out; the exit
    status is 1 when any was."""
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
    plan = series.plan_series(stored, **plan_options(args))
    for note in plan.notes:
        say(note)
    scenes = series.frame_scenes(plan, stored, folder, args.res, args.spp, args.orbit,
                                 mode=getattr(args, "mode", None))
    t0 = time.perf_counter()
    images = [r.image for r in render_cli_jobs(args, cli_jobs(args, [(str(s), {}) for s in scenes]))]
    seconds = time.perf_counter() - t0
    images = [check_finite(im, f"the frame of {src}") for (src, _), im in zip(stored, images)]
    clean = denoised(images) if args.denoise else None       # the movie shows the denoised frames
    if args.movie:
        movie = series.encode_movie(clean or images, args.movie, args.fps)
        say(f"wrote {movie} ({len(images)} {'denoised ' if clean else ''}frames at {args.fps} fps)")
    if args.frames or not args.movie:
        for k, img in enumerate(images):
            path = out.with_name(f"{out.stem}_{k:03d}{out.suffix}")
            write_frame(path, img)
            if clean:
                write_frame(denoised_path(path), clean[k])
        say(f"wrote {out.stem}_000{out.suffix} ... {out.stem}_{len(images) - 1:03d}{out.suffix} (+ .png"
            f"{', -denoised' if clean else ''})")
    say(f"{len(images)} frame(s) of {len(outputs)} outputs in {seconds:.2f} s; scenes and data in {folder}")
    series.report_failed(failed, sys.stderr)      # the stream of now (a default is bound at import)
    return 1 if failed else 0
