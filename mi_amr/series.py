"""A simulation's outputs over time as one scene plan: frames and movies.

``mi-amr render 'DD00??/DD00??' --field density --movie out.mp4`` renders
every output a pattern names with one plan (`plan_series`): the camera and
extent of the first output, and the TF ranges and scales from one
volume-weighted histogram over *all* outputs, so that colours mean the same
value in every frame. Each output is read once and kept as a native
``.amrb`` file in a folder beside the movie (`mi_amr.data.amrb`: it reopens
at disk speed for the histogram pass, the frame's XML scene and Dask
workers). An output that is missing or cannot be read is named and left
out; the others still render. `encode_movie` writes the frames as H.264
with the ffmpeg that ``imageio-ffmpeg`` ships.
"""

from __future__ import annotations

import dataclasses
import glob
import sys
from pathlib import Path

import numpy as np

from .autoscene import plan_scene
from .scene_writer import write_scene_xml
from .data.opening import open_data
from .data.amrb import read_amrb
from .native_file import save_native
from .data.volume import as_volume
from .data.yt_import import field_key
from .images import srgb8

#: Frames per second of a movie unless told otherwise.
FPS = 10


def expand_outputs(pattern: str) -> list[str]:
    """The outputs a shell-style pattern names, sorted (``DD00??/DD00??``);
    a pattern with no wildcard is itself. A pattern that names nothing is a
    ValueError naming it."""
    if not glob.has_magic(pattern):
        return [pattern]
    found = sorted(glob.glob(pattern))
    if not found:
        raise ValueError(f"{pattern}: no output matches this pattern")
    return found


class StoredVolumes:
    """The outputs' native files, opened one at a time on each pass (the
    histograms of `mi_amr.autoscene` take two passes over all of them):
    never more than one output in memory."""

    def __init__(self, paths):
        self.paths = [Path(p) for p in paths]

    def __iter__(self):
        for p in self.paths:
            yield read_amrb(p)

    def __len__(self):
        return len(self.paths)


def store_outputs(outputs, field, folder, fields=(), log=print):
    """Read each output (`mi_amr.data.opening.open_data`: anything yt loads,
    or a data file) and keep it as ``folder/NNN_NAME.amrb``. Returns
    ``(stored, failed)``: ``[(output, amrb path)]`` and ``[(output,
    message)]`` for those that could not be read (each named through
    ``log`` as it fails)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    stored, failed = [], []
    for k, src in enumerate(outputs):
        try:
            if not Path(src).exists():
                raise FileNotFoundError(f"{src}: no such file or directory")
            volume, _, _ = open_data(src, field, fields)
            volume = as_volume(volume)
            path = save_native(volume, folder / f"{k:03d}_{Path(src).name}.amrb")
            stored.append((src, path))
        except Exception as e:                   # named, and the others go on
            message = f"{type(e).__name__}: {e}"
            failed.append((src, message))
            log(f"mi-amr: skipping {src}: {message}")
    return stored, failed


def plan_series(stored, **options):
    """One `ScenePlan` for every stored output: the first output's domain
    and camera, TF ranges and scales from all of them (``options`` go to
    `mi_amr.autoscene.plan_scene`; an emission field is the stored one)."""
    if options.get("emission_field"):
        options["emission_field"] = field_key(options["emission_field"])
    plan = plan_scene(stored[0][1], None, stats=StoredVolumes([p for _, p in stored]), **options)
    plan.notes.append(f"one plan for {len(stored)} outputs: TF ranges from the histogram over all of them")
    return plan


def orbit(plan, degrees: float):
    """``plan`` with its camera turned by ``degrees`` about the up axis
    (z) through the target."""
    a = np.radians(degrees)
    c, s = np.cos(a), np.sin(a)
    o = np.asarray(plan.origin, float) - np.asarray(plan.target, float)
    turned = np.array([c * o[0] - s * o[1], s * o[0] + c * o[1], o[2]]) + np.asarray(plan.target, float)
    return dataclasses.replace(plan, origin=turned)


def frame_scenes(plan, stored, folder, res: int, spp: int, orbit_degrees: float = 0.0, mode: str | None = None):
    """One XML scene per stored output (``folder/NNN.xml``), the camera
    turned by ``orbit_degrees * k / n`` for frame ``k`` of ``n``; ``mode``:
    the lighting mode each scene names (None: the integrator's default)."""
    n = len(stored)
    scenes = []
    for k, (_, path) in enumerate(stored):
        p = orbit(plan, orbit_degrees * k / n) if orbit_degrees else plan
        scenes.append(write_scene_xml(p, Path(path).resolve(), Path(folder) / f"{k:03d}.xml", res=res, spp=spp,
                                      mode=mode))
    return scenes


def encode_movie(images, path, fps: int = FPS) -> Path:
    """Write linear RGB frames (H x W x 3, all one size) as an H.264 movie
    (sRGB, yuv420p: plays everywhere), through imageio-ffmpeg's ffmpeg."""
    try:
        import imageio_ffmpeg
    except ImportError as e:
        raise ImportError("--movie needs imageio-ffmpeg (it ships its own ffmpeg): "
                          "pip install 'mi-amr[movie]'") from e
    path = Path(path)
    frames = [srgb8(np.asarray(im, np.float32)[..., :3]) for im in images]
    h, w = frames[0].shape[:2]
    if h % 2 or w % 2:                     # yuv420p needs even sizes: pad by one row/column
        frames = [np.pad(f, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge") for f in frames]
        h, w = frames[0].shape[:2]
    writer = imageio_ffmpeg.write_frames(str(path), (w, h), fps=fps, codec="libx264", pix_fmt_out="yuv420p",
                                         quality=8, macro_block_size=2, ffmpeg_log_level="error")
    writer.send(None)
    for f in frames:
        writer.send(np.ascontiguousarray(f))
    writer.close()
    return path


def report_failed(failed, out=sys.stderr):
    """One line per output left out."""
    for src, message in failed:
        print(f"mi-amr: left out {src} ({message})", file=out)
