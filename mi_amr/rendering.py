"""Rendering as a library: what ``mi-amr render`` does, called from Python
with no command line (the command line, `mi_amr.render`, is a caller).

A `RenderJob` names one picture: an XML scene (with its ``<default>``
values) or data (a path of any kind `mi_amr.data.opening` reads, a yt data
set, `AMRCells`, a `BlockVolume`, or a `ScenePlan` made before), with the
options of the plan (`mi_amr.autoscene.plan_scene`), the lighting mode, the
samples per pixel, the image size and the seed. `render_jobs` renders
jobs here, or frame-parallel on a Dask cluster (``cluster``: a
``dask.distributed.Client``), and returns one `RenderResult` each: the image
(float32 ``(H, W, C)``, linear), the plan of a data job and the seconds.

It writes nothing and prints nothing: the command line writes the images
(`mi_amr.render.write_frame`) and the planned scene's XML, and shows the
plan's notes; a progress bar only with ``progress=True``. Bad jobs are
`ValueError`s naming the option, raised before any data are read.
"""

from __future__ import annotations

import os
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field as dc_field
from pathlib import Path

import numpy as np

from . import distributed
from .autoscene import ScenePlan, plan_scene
from .scene_writer import scene_for
from .plugins.integrator import MODES

#: Samples per pixel when neither the job nor its XML scene says.
DEFAULT_SPP = 64
#: The plan options a data job takes (`mi_amr.autoscene.plan_scene`).
PLAN_OPTIONS = ("tf", "log", "value_range", "density_scale", "emission", "emission_field", "emission_log",
                "emission_range", "emission_scale")


@dataclass
class RenderJob:
    """One picture. ``source``: an XML scene path, or data (see the module
    docstring); ``field``: the data's field (yt data); ``plan_options``:
    `PLAN_OPTIONS` for data; ``mode``: the ``amrvolpath`` lighting mode
    (None: the scene's own, ``multi`` for data); ``spp``: samples per pixel
    (None: the XML scene's ``sample_count``, else `DEFAULT_SPP`); ``res``:
    width and height of a data scene, pixels; ``defines``: an XML scene's
    ``<default>`` values (``-D NAME=VALUE``); ``seed``: of the first chunk."""
    source: object
    field: str | None = None
    plan_options: dict = dc_field(default_factory=dict)
    mode: str | None = None
    spp: int | None = None
    res: int = 400
    seed: int = 0
    defines: dict = dc_field(default_factory=dict)

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


@dataclass
class RenderResult:
    """A job's picture: ``image`` float32 (H, W, C) linear, ``plan`` (data
    jobs: what was planned, with its notes and predicted picture; None for
    XML), ``spp`` it was rendered with, ``seconds`` of its rendering (a
    cluster's frames share the batch's time)."""
    job: RenderJob
    image: np.ndarray
    plan: ScenePlan | None
    spp: int
    seconds: float


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
    """The samples per pixel ``job`` renders with."""
    if job.spp is not None:
        return int(job.spp)
    if job.is_xml:
        return scene_spp(job.source, job.defines) or DEFAULT_SPP
    return int(job.defines.get("spp", DEFAULT_SPP))


def render_jobs(jobs, cluster=None, *, chunk_spp: int | None = None, progress: bool = False,
                desc: str | None = None, drjit_threads: int | None = None) -> list[RenderResult]:
    """Render ``jobs`` (`RenderJob`s) and return their `RenderResult`s in
    order. ``cluster``: a ``dask.distributed.Client`` (frames in parallel;
    a data job goes as its scene dictionary) or None (here, one after the
    other); data jobs are planned here unless their ``source`` is a
    `ScenePlan` already; ``chunk_spp``: samples per chunk (default an
    eighth of the job's spp; the image depends on the chunks, not on where
    they run); ``desc``: the progress bar's label. The Mitsuba variant must be set."""
    jobs = list(jobs)
    for job in jobs:
        job.check()
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
        return [RenderResult(j, _image(im), p, spp, seconds) for j, p, im in zip(jobs, plans, images)]
    for job, plan, spp, (scene, params) in zip(jobs, plans, spps, frames):
        t0 = time.perf_counter()
        if cluster is not None:
            image = distributed.render_frames([(scene, params)], spp, cluster, chunk_for(spp, chunk_spp), job.seed,
                                              progress=progress, desc=desc or _label(job),
                                              drjit_threads=drjit_threads, integrator=_integrator(job))[0]
        else:
            image = distributed.render_local(scene, spp, chunk_for(spp, chunk_spp), job.seed, params=params,
                                             progress=progress, desc=desc or _label(job),
                                             integrator=_integrator(job))
        results.append(RenderResult(job, _image(image), plan, spp, time.perf_counter() - t0))
    return results


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
