"""Sample-parallel rendering, in this process or on a Dask cluster.

A render of ``spp`` samples is cut into *chunks* of at most ``chunk_spp``
samples, each rendered with its own seed (`chunk_seeds`). A chunk returns the
film's raw weighted sums (``film.bitmap(raw=True)``: premultiplied channels
and the filter weight ``W``), not a normalised image; the sums of all chunks,
added in chunk order and divided by the summed weight, are the image one
render of ``spp`` samples gives, for every reconstruction filter
(docs/design.md section 10).

* `render_local`: the chunks one after the other in this process (what
  ``mi-amr render`` does without ``--workers``).
* `render`: the same chunks as Dask tasks. Each worker loads a scene once
  and keeps it (data files are read on the worker; a scene dictionary is
  sent to every worker once, not with each task). A worker that dies loses
  only its running chunk, which Dask runs again elsewhere; a chunk that
  raises fails the render with its error.

Dask (``pip install mi-amr[distributed]``) is imported only here, and only
when a render needs it.
"""

from __future__ import annotations

import os
import pickle
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
from tqdm import tqdm

from .scene_xml import dict_with_integrator_parameters, with_integrator_parameters

#: Chunks of one render: their seeds are ``seed * MAX_CHUNKS + index``.
MAX_CHUNKS = 1 << 16
#: Default samples per chunk: large enough that scheduling a chunk (a few ms)
#: is far below rendering it, small enough to spread a render over workers.
DEFAULT_CHUNK_SPP = 16


@dataclass(frozen=True)
class SceneSpec:
    """What a worker needs to load a scene: an XML file with ``-D``-style
    parameters (``path`` None: the scene dictionary sent with the task)."""
    path: str | None = None
    params: tuple = ()
    variant: str = "llvm_ad_rgb"
    sensor: int = 0
    drjit_threads: int | None = None
    #: ``(name, value)`` set on the scene's ``amrvolpath`` integrator (e.g.
    #: ``mode``; `mi_amr.scene_xml.with_integrator_parameters`)
    integrator: tuple = ()
    #: identifies the scene within a worker's cache
    key: str = field(default_factory=lambda: uuid.uuid4().hex)


def chunk_plan(spp: int, chunk_spp: int | None = None) -> list[int]:
    """Samples of each chunk: ``spp`` cut into pieces of at most ``chunk_spp``
    that differ by at most one."""
    spp = int(spp)
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    chunk_spp = DEFAULT_CHUNK_SPP if chunk_spp is None else int(chunk_spp)
    if chunk_spp < 1:
        raise ValueError(f"chunk_spp must be >= 1, got {chunk_spp}")
    n = -(-spp // chunk_spp)
    if n > MAX_CHUNKS:
        raise ValueError(f"{n} chunks of {chunk_spp} spp: at most {MAX_CHUNKS} (raise chunk_spp)")
    return [spp // n + (1 if i < spp % n else 0) for i in range(n)]


def chunk_seeds(seed: int, n: int) -> list[int]:
    """Seeds of chunks ``0..n-1`` of a render with ``seed``: distinct within a
    render, and across renders whose seeds differ (below 2^16)."""
    seed = int(seed)
    if not 0 <= seed < (1 << 32) // MAX_CHUNKS:
        raise ValueError(f"seed must be in [0, {(1 << 32) // MAX_CHUNKS}), got {seed}")
    return [seed * MAX_CHUNKS + i for i in range(n)]


def scene_spec(scene, params: dict | None = None, variant: str | None = None, sensor: int = 0,
               drjit_threads: int | None = None, integrator: dict | None = None) -> SceneSpec:
    """A `SceneSpec` of an XML path (``params``: its ``-D`` parameters;
    ``integrator``: parameters set on its ``amrvolpath`` integrator)."""
    variant = variant or mi.variant() or "llvm_ad_rgb"
    if isinstance(scene, dict):
        return SceneSpec(variant=variant, sensor=sensor, drjit_threads=drjit_threads)
    path = Path(scene)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such scene file")
    return SceneSpec(path=str(path.resolve()), params=tuple(sorted((params or {}).items())),
                     variant=variant, sensor=sensor, drjit_threads=drjit_threads,
                     integrator=tuple(sorted((integrator or {}).items())))


def load_scene(path, params: dict | None = None, integrator: dict | None = None, parallel: bool = True):
    """The XML scene at ``path`` with its ``-D`` ``params``, and
    ``integrator`` parameters set on its ``amrvolpath`` integrator (e.g.
    ``{"mode": "single"}``: ``mi-amr render --mode``)."""
    if integrator:
        return with_integrator_parameters(str(path), dict(integrator), parallel=parallel, **(params or {}))
    return mi.load_file(str(path), parallel=parallel, **(params or {}))


# ---- One chunk (runs on a worker, or here) ----------------------------------
_SCENES: dict = {}


def _scene(spec: SceneSpec, scene_dict=None):
    """The scene of ``spec``, loaded once per process."""
    if mi.variant() != spec.variant:
        mi.set_variant(spec.variant)
    if spec.drjit_threads is not None:
        if dr.thread_count() != spec.drjit_threads:
            dr.set_thread_count(spec.drjit_threads)
    key = (spec.variant, spec.key)
    if key not in _SCENES:
        if spec.path is not None:
            _SCENES[key] = load_scene(spec.path, dict(spec.params), dict(spec.integrator))
        else:
            _SCENES[key] = mi.load_dict(_from_portable(scene_dict))
    return _SCENES[key]


# Scene dictionaries cross process boundaries pickled; Mitsuba's transforms do
# not pickle, so they travel as their 4x4 matrices.
_TRANSFORM = "__mi_amr_transform4f__"


def _to_portable(obj, where="scene"):
    """``obj`` with every Mitsuba transform replaced by its matrix; a value
    that cannot be pickled raises a TypeError naming where it is."""
    if isinstance(obj, dict):
        return {k: _to_portable(v, f"{where}[{k!r}]") for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_to_portable(v, f"{where}[{i}]") for i, v in enumerate(obj))
    if type(obj).__name__.endswith("Transform4f") and hasattr(obj, "matrix"):
        return (_TRANSFORM, np.array(obj.matrix, dtype=np.float64))
    try:
        pickle.dumps(obj)
    except Exception as e:
        raise TypeError(f"{where}: a {type(obj).__name__} cannot be sent to Dask workers ({e}); "
                        "give plain values, or an XML scene file") from e
    return obj


def _from_portable(obj):
    if isinstance(obj, dict):
        return {k: _from_portable(v) for k, v in obj.items()}
    if isinstance(obj, tuple) and len(obj) == 2 and isinstance(obj[0], str) and obj[0] == _TRANSFORM:
        return mi.ScalarTransform4f(mi.ScalarMatrix4f(obj[1].astype(np.float32)))
    if isinstance(obj, (list, tuple)):
        return type(obj)(_from_portable(v) for v in obj)
    return obj


def render_chunk(spec: SceneSpec, spp: int, seed: int, scene_dict=None) -> np.ndarray:
    """Render one chunk: the film's raw weighted sums (H, W, C + 1), float32,
    the weight last."""
    scene = _scene(spec, scene_dict)
    mi.render(scene, spp=int(spp), seed=int(seed), sensor=spec.sensor)
    film = scene.sensors()[spec.sensor].film()
    return np.array(film.bitmap(raw=True), dtype=np.float32, copy=True)


def forget_scene(spec: SceneSpec):
    """Drop a scene from this process's cache."""
    _SCENES.pop((spec.variant, spec.key), None)


def merge(sums) -> np.ndarray:
    """The image of chunk sums added in the order given: channels divided by
    the summed weight (0 where no sample landed), float32 (H, W, C)."""
    total = None
    for s in sums:
        total = s.astype(np.float64) if total is None else total + s
    w = total[..., -1:]
    img = np.where(w > 0, total[..., :-1] / np.where(w > 0, w, 1.0), 0.0)
    return img.astype(np.float32)


# ---- In this process ---------------------------------------------------------
def load_here(scene, params: dict | None = None, integrator: dict | None = None) -> mi.Scene:
    """``scene`` loaded in this process as `render_local` renders it: an
    XML path (``params``: its ``-D`` parameters), a scene dictionary or a
    loaded ``mi.Scene`` (returned as it is); ``integrator``: parameters set
    on the XML or dictionary scene's ``amrvolpath`` integrator."""
    if isinstance(scene, mi.Scene):
        if integrator:
            raise ValueError("integrator parameters are for a scene file or dictionary, not a loaded scene")
        return scene
    if isinstance(scene, dict):
        return mi.load_dict(dict_with_integrator_parameters(scene, integrator) if integrator else scene,
                            parallel=False)
    # on this thread: Mitsuba's parallel loader may build a medium on a worker
    # thread, where Ctrl-C cannot reach it until the whole load is over
    return load_scene(scene, params, integrator, parallel=False)


def render_local(scene, spp: int, chunk_spp: int | None = None, seed: int = 0, sensor: int = 0,
                 params: dict | None = None, progress: bool = False, desc: str = "render",
                 integrator: dict | None = None):
    """Render the chunks of ``spp`` one after the other here; same chunks,
    seeds and merge as `render` on a cluster, so the same image. ``scene``:
    an XML path (``params``: its ``-D`` parameters), a scene dictionary or a
    loaded ``mi.Scene``; ``integrator``: parameters set on the (XML or
    dictionary) scene's ``amrvolpath`` integrator, e.g. ``{"mode": "single"}``."""
    plan = chunk_plan(spp, chunk_spp)
    seeds = chunk_seeds(seed, len(plan))
    loaded = load_here(scene, params, integrator)
    sums = []
    with tqdm(total=spp, unit="spp", desc=desc, disable=not progress) as bar:
        for n, s in zip(plan, seeds):
            mi.render(loaded, spp=n, seed=s, sensor=sensor)
            film = loaded.sensors()[sensor].film()
            sums.append(np.array(film.bitmap(raw=True), dtype=np.float32, copy=True))
            bar.update(n)
    return mi.TensorXf(merge(sums))


# ---- On a Dask cluster -----------------------------------------------------
def local_cluster(workers: int | None = None):
    """A Dask ``Client`` on a ``LocalCluster`` of ``workers`` processes (one
    per core by default), one thread each."""
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError as e:
        raise ImportError("mi_amr.distributed needs Dask: pip install 'mi-amr[distributed]'") from e
    workers = workers or os.cpu_count() or 1
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                           dashboard_address=":0")
    return Client(cluster)


def render(scene, spp: int, client=None, chunk_spp: int | None = None, seed: int = 0, sensor: int = 0,
           progress: bool = False, **params):
    """Render ``scene`` with ``spp`` samples on a Dask cluster and return the
    image (``mi.TensorXf``, as ``mi.render`` gives it).

    ``scene``: an XML path (``params`` are its ``-D`` parameters) or a scene
    dictionary. ``client``: a ``dask.distributed.Client``; None starts a
    `local_cluster` (one process per core) for this render. The image equals
    `render_local` with the same ``seed`` and ``chunk_spp`` (to float
    rounding of the film's sums)."""
    return render_frames([(scene, params)], spp, client, chunk_spp, seed, sensor, progress)[0]


def render_frames(frames, spp: int, client=None, chunk_spp: int | None = None, seed: int = 0,
                  sensor: int = 0, progress: bool = False, desc: str = "render",
                  drjit_threads: int | None = None, integrator: dict | None = None):
    """Render several ``(scene, params)`` frames at once (all their chunks
    are scheduled together) and return their images in order.
    ``drjit_threads``: Dr.Jit threads per worker (default: all cores, or one
    on the local cluster this call starts, which has a process per core);
    ``integrator``: parameters set on each scene's ``amrvolpath`` integrator
    (as `render_local`)."""
    own = client is None
    if own:
        client = local_cluster()
    from dask.distributed import as_completed
    try:
        threads = 1 if own and drjit_threads is None else drjit_threads
        plan = chunk_plan(spp, chunk_spp)
        seeds = chunk_seeds(seed, len(plan))
        futures, specs = {}, []
        for f, (scene, params) in enumerate(frames):
            if isinstance(scene, dict) and integrator:
                scene = dict_with_integrator_parameters(scene, integrator)
            spec = scene_spec(scene, params, sensor=sensor, drjit_threads=threads, integrator=integrator)
            specs.append(spec)
            # a scene dictionary goes to every worker once; tasks name it
            # (in a list: scatter takes a dict for many named values)
            data = (client.scatter([_to_portable(scene)], broadcast=True, hash=False)[0]
                    if isinstance(scene, dict) else None)
            for i, (n, s) in enumerate(zip(plan, seeds)):
                fut = client.submit(render_chunk, spec, n, s, data, key=f"mi-amr-chunk-{spec.key}-{i}",
                                    pure=False)
                futures[fut] = (f, i, n)
        sums = [[None] * len(plan) for _ in frames]
        try:
            with tqdm(total=spp * len(frames), unit="spp", desc=desc, disable=not progress) as bar:
                for fut in as_completed(list(futures)):
                    f, i, n = futures[fut]
                    sums[f][i] = fut.result()        # a chunk's error is raised here
                    bar.update(n)
        except BaseException:
            client.cancel(list(futures))
            raise
        client.run(_forget_all, [s for s in specs])
        return [mi.TensorXf(merge(s)) for s in sums]
    finally:
        if own:
            cluster = client.cluster
            client.close()
            cluster.close()


def _forget_all(specs):
    for s in specs:
        forget_scene(s)
