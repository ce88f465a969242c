"""Rendering as a library: what ``mi-amr render`` does, called from Python
with no command line (the command line, `mi_amr.tools.render`, is a caller).

A `RenderJob` names one picture: an XML scene (with its ``<default>``
values) or data (a path of any kind `mi_amr.data.opening` reads, a yt data
set, `AMRCells`, a `BlockVolume`, or a `ScenePlan` made before), with the
options of the plan (`mi_amr.autoscene.plan_scene`), the lighting mode, the
samples per pixel, the image size and the seed. `render_jobs` renders
jobs here, or frame-parallel on a Dask cluster (``cluster``: a
``dask.distributed.Client``), and returns one `RenderResult` each: the image
(float32 ``(H, W, C)``, linear), the plan of a data job and the seconds.

A job with ``noise`` renders adaptively (`mi_amr.adaptive`: tiles stop at
that relative error, ``spp`` is the cap, ``seconds`` a time limit; its
result has the samples each pixel took), here only: a cluster renders fixed
counts. A job with ``denoise`` also gets the picture through Open Image
Denoise (`mi_amr.denoising`); its ``image`` stays the unbiased estimate.

It writes nothing and prints nothing: the command line writes the images
(`mi_amr.tools.render.write_frame`) and the planned scene's XML, and shows the
plan's notes; a progress bar only with ``progress=True``. Bad jobs are
`ValueError`s naming the option, raised before any data are read.

The Mitsuba variant is chosen here for every caller (`use_variant`): the
one the user set, else ``cuda_ad_rgb`` where a CUDA device works and
``llvm_ad_rgb`` elsewhere (`default_variant`), said once per process.
"""

from __future__ import annotations

import os
import sys
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field as dc_field
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from tqdm import tqdm

from . import adaptive, denoising, distributed
from .autoscene import ScenePlan, plan_scene
from .scene_writer import scene_for
from .plugins.integrator import MODES
from .transfer.spectra import refusal

#: Samples per pixel when neither the job nor its XML scene says.
DEFAULT_SPP = 64
#: Samples per pixel of data rendered in ``ray_march`` by default: its
#: picture has no noise (docs/design.md section 14), the samples only
#: antialias the pixel's footprint.
MARCH_SPP = 4


def default_spp(mode: str | None) -> int:
    """Samples per pixel of data when none is asked for, in lighting ``mode``."""
    return MARCH_SPP if mode == "ray_march" else DEFAULT_SPP
#: The plan options a data job takes (`mi_amr.autoscene.plan_scene`).
PLAN_OPTIONS = ("tf", "log", "value_range", "density_scale", "emission", "emission_field", "emission_log",
                "emission_range", "emission_scale", "iso", "iso_only")


#: The variants chosen when none is set, in order: the first whose Dr.Jit
#: backend works here (`default_variant`).
DEFAULT_VARIANTS = (("cuda_ad_rgb", dr.JitBackend.CUDA), ("llvm_ad_rgb", dr.JitBackend.LLVM))


def default_variant() -> str:
    """``cuda_ad_rgb`` where Dr.Jit finds a CUDA device, else ``llvm_ad_rgb``
    (what ``mi-amr render`` and ``mi_amr.scene`` render in when no variant
    is set); a one-line `OSError` when neither backend works."""
    for variant, backend in DEFAULT_VARIANTS:
        if variant in mi.variants() and dr.has_backend(backend):
            return variant
    raise OSError("no Mitsuba variant can render here: no CUDA device, and Dr.Jit's LLVM backend found no "
                  "libLLVM (install Debian's libllvm19 or set DRJIT_LIBLLVM_PATH; docs/manual/setup.md)")


def use_variant(variant: str | None = None, say=True) -> str:
    """Make the Mitsuba variant to render in active and return its name:
    ``variant`` when given (set for the process, as ``mi.set_variant``
    does), else the one set before, else `default_variant` (said in one
    line on stderr unless ``say`` is false: once, as it stays set). A variant that
    is not there, or that the plugins cannot render in (scalar, polarized:
    `mi_amr.transfer.spectra.refusal`), is a one-line `ValueError` and
    nothing changes."""
    chosen = variant or mi.variant()
    if chosen is None:
        chosen = default_variant()
        if say:
            why = "a CUDA device works here" if chosen.startswith("cuda") else "no CUDA device here"
            print(f"mi-amr: rendering in Mitsuba's {chosen} ({why}; mi.set_variant(...) or variant= chooses "
                  "another)", file=sys.stderr)
    if chosen not in mi.variants():
        raise ValueError(f"variant {chosen!r} is not available (available: {', '.join(mi.variants())})")
    why = refusal(chosen)
    if why is not None:
        raise ValueError(f"mi-amr cannot render in the variant {chosen!r}: {why}")
    if mi.variant() != chosen:
        mi.set_variant(chosen)
    return chosen


@dataclass
class RenderJob:
    """One picture. ``source``: an XML scene path, or data (see the module
    docstring); ``field``: the data's field (yt data); ``plan_options``:
    `PLAN_OPTIONS` for data; ``mode``: the ``amrvolpath`` lighting mode
    (None: the scene's own, ``multi`` for data); ``spp``: samples per pixel
    (None: the XML scene's ``sample_count``, else `default_spp` of the mode); ``res``:
    width and height of a data scene, pixels; ``defines``: an XML scene's
    ``<default>`` values (``-D NAME=VALUE``); ``seed``: of the first chunk.
    ``noise``: render adaptively, tiles stopping at this relative error
    (`mi_amr.adaptive`; then ``spp`` is the cap, None:
    `mi_amr.adaptive.DEFAULT_MAX_SPP`), None: ``spp`` in every pixel;
    ``seconds``: the adaptive render's time limit; ``denoise``: also the
    denoised picture (`RenderResult.denoised`)."""
    source: object
    field: str | None = None
    plan_options: dict = dc_field(default_factory=dict)
    mode: str | None = None
    spp: int | None = None
    res: int = 400
    seed: int = 0
    defines: dict = dc_field(default_factory=dict)
    noise: float | None = None
    seconds: float | None = None
    denoise: bool = False

    @property
    def is_xml(self) -> bool:
        return isinstance(self.source, (str, Path)) and Path(str(self.source)).suffix.lower() == ".xml"

    def check(self):
        """A `ValueError` naming the first bad option (nothing is read)."""
        if self.spp is not None and (not isinstance(self.spp, (int, np.integer)) or self.spp < 1):
            raise ValueError(f"spp: at least 1, got {self.spp!r}")
        if not isinstance(self.res, (int, np.integer)) or not 1 <= self.res <= 1 << 15:
            raise ValueError(f"res: an image width from 1 to 32768 pixels, got {self.res!r}")
        if self.mode is not None and self.mode not in MODES:
            raise ValueError(f"mode: one of {', '.join(MODES)}, got {self.mode!r}")
        unknown = sorted(set(self.plan_options) - set(PLAN_OPTIONS))
        if unknown:
            raise ValueError(f"plan options: unknown {', '.join(unknown)} (known: {', '.join(PLAN_OPTIONS)})")
        if self.is_xml and (self.field is not None or self.plan_options):
            raise ValueError("field and plan options are for data, not XML scenes (set those in the scene)")
        if not self.is_xml and self.defines and set(self.defines) - {"res", "spp"}:
            raise ValueError("defines other than res and spp are for XML scenes")
        if self.noise is not None and not (isinstance(self.noise, (int, float)) and 0 < self.noise < 1e3):
            raise ValueError(f"noise: a relative error above 0 (e.g. 0.02), got {self.noise!r}")
        if self.seconds is not None and not (isinstance(self.seconds, (int, float)) and self.seconds > 0
                                             and np.isfinite(self.seconds)):
            raise ValueError(f"seconds: a time limit above 0, got {self.seconds!r}")
        if self.seconds is not None and self.noise is None:
            raise ValueError("seconds: a time limit is for adaptive jobs (give noise too)")


@dataclass
class RenderResult:
    """A job's picture: ``image`` float32 (H, W, C) linear, ``plan`` (data
    jobs: what was planned, with its notes and predicted picture; None for
    XML), ``spp`` it was rendered with, ``seconds`` of its rendering (a
    cluster's frames share the batch's time); an adaptive job's
    ``adaptive`` (`mi_amr.adaptive.AdaptiveResult`: the samples each pixel
    took, ``spp`` their most), a ``denoise`` job's ``denoised`` picture
    (float32 (H, W, 3))."""
    job: RenderJob
    image: np.ndarray
    plan: ScenePlan | None
    spp: int
    seconds: float
    adaptive: adaptive.AdaptiveResult | None = None
    denoised: np.ndarray | None = None


def scene_spp(path, params: dict) -> int | None:
    """The ``sample_count`` of an XML scene's first sensor (a ``$name``
    taken from ``params``, the ``-D`` values, else the scene's
    ``<default>``); None when the scene names none (or does not parse:
    its load says why)."""
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError):
        return None
    sensor = root.find("sensor")
    sampler = sensor.find("sampler") if sensor is not None else None
    counts = [e.get("value", "") for e in (sampler if sampler is not None else []) if e.get("name") == "sample_count"]
    if not counts:
        return None
    value = counts[0]
    if value.startswith("$"):
        defaults = {e.get("name"): e.get("value") for e in root.findall("default")}
        value = params.get(value[1:], defaults.get(value[1:], ""))
    try:
        return int(value) if int(value) >= 1 else None
    except ValueError:
        return None


def plan_job(job: RenderJob) -> ScenePlan:
    """The `ScenePlan` of a data job (its ``source`` itself when it is one)."""
    if isinstance(job.source, ScenePlan):
        return job.source
    return plan_scene(job.source, job.field, **job.plan_options)


def job_spp(job: RenderJob) -> int:
    """The samples per pixel ``job`` renders with (adaptive: at most)."""
    if job.spp is not None:
        return int(job.spp)
    if job.noise is not None:
        return adaptive.DEFAULT_MAX_SPP
    if job.is_xml:
        return scene_spp(job.source, job.defines) or DEFAULT_SPP
    return int(job.defines.get("spp", default_spp(job.mode)))


def render_jobs(jobs, cluster=None, *, chunk_spp: int | None = None, progress: bool = False,
                desc: str | None = None, drjit_threads: int | None = None,
                variant: str | None = None) -> list[RenderResult]:
    """Render ``jobs`` (`RenderJob`s) and return their `RenderResult`s in
    order. ``cluster``: a ``dask.distributed.Client`` (frames in parallel;
    a data job goes as its scene dictionary) or None (here, one after the
    other); data jobs are planned here unless their ``source`` is a
    `ScenePlan` already; ``chunk_spp``: samples per chunk (default an
    eighth of the job's spp; the image depends on the chunks, not on where
    they run); ``desc``: the progress bar's label; ``variant``: the Mitsuba
    variant (None: the one set, else `default_variant`; `use_variant`), which
    a cluster's workers render in too."""
    jobs = list(jobs)
    for job in jobs:
        job.check()
        if cluster is not None and job.noise is not None:
            raise ValueError("noise: adaptive sampling renders in this process, not on a cluster "
                             "(noise=None renders spp samples in every pixel there)")
    use_variant(variant)
    plans = [None if j.is_xml else plan_job(j) for j in jobs]
    frames, spps = [], []
    for job, plan in zip(jobs, plans):
        spp = job_spp(job)
        spps.append(spp)
        if job.is_xml:
            frames.append((str(job.source), dict(job.defines)))
        else:
            res = int(job.defines.get("res", job.res))
            frames.append((scene_for(plan, res=res, spp=spp), {}))
    results = []
    same = len({(s, j.seed, j.mode) for s, j in zip(spps, jobs)}) == 1
    if cluster is not None and same and jobs:
        spp, job = spps[0], jobs[0]
        t0 = time.perf_counter()
        images = distributed.render_frames(frames, spp, cluster, chunk_for(spp, chunk_spp), job.seed,
                                           progress=progress, desc=desc or _label(job), drjit_threads=drjit_threads,
                                           integrator=_integrator(job))
        seconds = time.perf_counter() - t0
        return [_denoised(RenderResult(j, _image(im), p, spp, seconds)) for j, p, im in zip(jobs, plans, images)]
    for job, plan, spp, (scene, params) in zip(jobs, plans, spps, frames):
        t0 = time.perf_counter()
        if cluster is not None:
            image = distributed.render_frames([(scene, params)], spp, cluster, chunk_for(spp, chunk_spp), job.seed,
                                              progress=progress, desc=desc or _label(job),
                                              drjit_threads=drjit_threads, integrator=_integrator(job))[0]
            results.append(_denoised(RenderResult(job, _image(image), plan, spp, time.perf_counter() - t0)))
            continue
        loaded = distributed.load_here(scene, params, _integrator(job))
        if job.noise is None:
            image = distributed.render_local(loaded, spp, chunk_for(spp, chunk_spp), job.seed, progress=progress,
                                             desc=desc or _label(job))
            result = RenderResult(job, _image(image), plan, spp, time.perf_counter() - t0)
        else:
            found = render_adaptively(loaded, job, spp, progress, desc or _label(job))
            result = RenderResult(job, found.image, plan, int(found.spp.max()), time.perf_counter() - t0,
                                  adaptive=found)
        results.append(_denoised(result))
    return results


def render_adaptively(scene: mi.Scene, job: RenderJob, spp: int, progress: bool = False,
                      desc: str = "render") -> adaptive.AdaptiveResult:
    """``job`` (with ``noise``) rendered adaptively in the loaded ``scene``,
    at most ``spp`` samples per pixel; the progress bar counts the
    picture's mean samples per pixel."""
    with tqdm(total=spp, unit="spp", desc=desc, disable=not progress,
              bar_format="{l_bar}{bar}| {n:.1f}/{total} spp mean [{elapsed}]") as bar:
        def advance(mean_spp):
            bar.update(mean_spp - bar.n)
        return adaptive.render_adaptive(scene, job.noise, spp, job.seconds, job.seed, progress=advance)


def _denoised(result: RenderResult) -> RenderResult:
    """``result`` with its denoised picture when its job asks for one
    (`mi_amr.denoising.denoise`, without a guide: docs/performance/adaptive.md
    measured the albedo guide worse)."""
    if result.job.denoise:
        result.denoised = denoising.denoise(result.image)
    return result


def render_job(job: RenderJob, **options) -> RenderResult:
    """One `RenderJob` (see `render_jobs`)."""
    return render_jobs([job], **options)[0]


def chunk_for(spp: int, chunk_spp: int | None) -> int:
    """Samples per chunk: ``chunk_spp``, else an eighth of ``spp`` (the
    same here and on a cluster, so the same image)."""
    return chunk_spp or -(-spp // 8)


def _integrator(job: RenderJob) -> dict | None:
    return {"mode": job.mode} if job.mode else None


def _label(job: RenderJob) -> str:
    return Path(str(job.source)).name if isinstance(job.source, (str, Path, os.PathLike)) else "render"


def _image(image) -> np.ndarray:
    return np.array(image, dtype=np.float32)
