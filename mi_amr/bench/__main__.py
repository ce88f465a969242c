"""``python -m mi_amr.bench``: the benchmarks' command line (also ``mi-amr bench``).

`main` is `parse` (the options of every study), `dispatch` (which study the
options ask for) and that study's ``main_args``: the protocol
(`mi_amr.bench.protocol`, the default), ``--scale`` (`mi_amr.bench.scale`),
``--resample`` (`mi_amr.bench.resample`), ``--view`` (`mi_amr.bench.view`),
``--widget`` (`mi_amr.bench.widget`: the notebook widget's frames/s through
Jupyter's comm channel),
``--distributed`` (`mi_amr.bench.distributed`), ``--modes``
(`mi_amr.bench.modes`: frames/s per lighting mode, and the uniform field
against Mitsuba's homogeneous medium), ``--modes-bound``
(`mi_amr.bench.modes_bound`: what bounds the emission-absorption frame) or
``--grad`` (`mi_amr.bench.gradients`: what a gradient step costs against the
primal frame and a dense grid) or ``--march`` (`mi_amr.bench.march`: the
ray marcher against the path tracer's convergence frames, the paper's
comparison) or ``--vs-yt`` (`mi_amr.bench.vs_yt`: yt's
volume renderer against ``ray_march`` and ``emission_absorption``, time to
equal error) or ``--iso`` (`mi_amr.bench.iso`: isosurfaces against yt's
``ds.surface``, cracks and hit errors, and the isosurface frame's rate).
"""

import argparse
import sys

from ..data.datasets import LAYOUTS
from ..reconstruction import METHODS
from . import protocol
from .protocol import all_configs


def main(argv=None) -> int:
    return dispatch(parse(argv))


def dispatch(args) -> int:
    """Run the study the options ask for; its exit status."""
    if args.vs_yt is not None:
        from .vs_yt import main_args
    elif args.adaptive is not None:
        from .adaptive import main_args
    elif args.iso:
        from .iso import main_args
    elif args.view:
        from .view import main_args
    elif args.widget:
        from .widget import main_args
    elif args.distributed:
        from .distributed import main_args
    elif args.march:
        from .march import main_args
    elif args.modes_bound:
        from .modes_bound import main_args
    elif args.modes:
        from .modes import main_args
    elif args.grad:
        from .gradients import main_args
    elif args.scale:
        from .scale import main_args
    elif args.resample is not None:
        from .resample import main_args
    else:
        from .protocol import main_args
    return main_args(args)


def parse(argv=None) -> argparse.Namespace:
    """The options of ``python -m mi_amr.bench`` (``argv``: the process's)."""
    p = argparse.ArgumentParser(prog="python -m mi_amr.bench", description=protocol.__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="example:\n  python -m mi_amr.bench --quick --out out/bench-quick\n"
                                       "  python -m mi_amr.bench --datasets cloud --tfs spiky "
                                       "--configs reference amrvolpath/default --out out/b")
    for options in (protocol_options, scale_options, resample_options, view_options, distributed_options,
                    modes_options, grad_options, vs_yt_options, iso_options, adaptive_options):
        options(p)
    args = p.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)      # the command, for the tables
    return args


def protocol_options(p):
    p.add_argument("files", nargs="*", help="extra .cells data sets")
    p.add_argument("--out", required=True, help="results folder")
    p.add_argument("--quick", action="store_true", help="small sizes: minutes on 2 cores")
    p.add_argument("--cells", type=int, default=20000)
    p.add_argument("--res", type=int, default=256, help="frame width and height (default 256: frames of real size)")
    p.add_argument("--spp", type=int, default=16)
    p.add_argument("--ref-spp", type=int, default=1024)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--frozen", action=argparse.BooleanOptionalAction, default=True,
                   help="time frames of a dr.freeze-recorded render (as an interactive viewer runs them: "
                        "no per-frame Python trace), every configuration alike (default; --no-frozen times "
                        "plain mi.render frames)")
    p.add_argument("--limit", action=argparse.BooleanOptionalAction, default=True,
                   help="time the empty-medium frame of each case with the others (the limit: a medium "
                        "that costs nothing) and report each row's share of it, t_empty / t (default)")
    p.add_argument("--sparse-res", type=int, default=128,
                   help="grid size of the 'sparse' data set (the cloud field on one uniform level; its "
                        "size does not follow --cells)")
    p.add_argument("--max-depth", type=int, default=64)
    p.add_argument("--datasets", nargs="*", default=["cloud", "shell", "stadium", "blocks"])
    p.add_argument("--tfs", nargs="*", default=["spiky", "foggy"])
    p.add_argument("--data", metavar="PATH",
                   help="run on this data set instead of the synthetic ones (.cells/.npz or anything yt "
                        "loads; log10 values and density scale chosen as mi-amr render chooses them)")
    p.add_argument("--field", help="field of --data or of --vs-yt DATA (e.g. density)")
    p.add_argument("--configs", nargs="*", default=None, help="subset of: " + " ".join(all_configs()))
    p.add_argument("--peers", nargs="*", default=[], choices=["eradiate"],
                   help="also render each case with these peers in their own environments (eradiate: "
                        "Eradiate's Mitsuba fork, extremum_grid + eovolpath; needs make peers)")
    p.add_argument("--reconstruction", default="nearest", choices=tuple(METHODS))
    p.add_argument("--grid-refinement", type=int, default=None, metavar="F",
                   help="grid_refinement of every amr medium (1: uniform grids only; default: the cost model's)")
    p.add_argument("--no-value-masks", action="store_true",
                   help="range majorants only (the A/B of the value masks; nearest)")
    p.add_argument("--memory-limit", type=float, default=4.0,
                   help="GiB allowed for the dense reference; larger data sets skip it")
    p.add_argument("--variant", default="llvm_ad_rgb",
                   help="Mitsuba variant: llvm_ad_rgb (default) or cuda_ad_rgb (a GPU; make test-gpu)")
    p.add_argument("--curve-spp", type=int, nargs="*", default=[1, 2, 4, 8],
                   help="sample counts of the error-against-time curves")
    p.add_argument("--sweep", type=int, nargs="*", default=[8, 12, 16, 24, 32, 48, 64, 96],
                   help="grid resolutions of the sweep (amrvolpath/grid/hash); empty: no sweep")


def scale_options(p):
    p.add_argument("--scale", type=float, nargs="+", default=None, metavar="CELLS",
                   help="run the scale benchmark instead, at these cell counts (e.g. 1e5 1e6 1e7 1e8)")
    p.add_argument("--scale-kinds", nargs="+", default=None,
                   help="data kinds of the scale benchmark: blocks (16^3), mixed (8^3-32^3), cloud "
                        "(octree-like, up to 1e7 cells); default all three")
    p.add_argument("--layouts", nargs="+", default=None, choices=list(LAYOUTS), metavar="LAYOUT",
                   help="scale benchmark: file layouts of the .cells data, rows of their own: blocks (the "
                        "generator's), zfast (z fastest inside blocks), level (blocks of one physical size, "
                        "fewer cells on coarser levels, grouped by level), space (blocks sorted by position), "
                        "shuffled (cells in random order); default blocks")
    p.add_argument("--scale-sources", nargs="+", default=None, choices=["cells", "amrb"],
                   help="files the scale benchmark opens: the .cells file, its .amrb conversion (default both)")
    p.add_argument("--scale-configs", nargs="+", default=None,
                   help="configurations of the scale benchmark (default: amrvolpath/grid/hash)")
    p.add_argument("--cold-kernels", action="store_true",
                   help="scale benchmark: each process starts with an empty Dr.Jit kernel cache")
    p.add_argument("--data-dir", default="out/data", help="where the scale benchmark keeps its .cells files")


def resample_options(p):
    p.add_argument("--resample", nargs="*", default=None, metavar="DATA",
                   help="time against error of the amr medium against dense resamples (see mi_amr.bench.resample): "
                        "cosmo:CELLS[:LEVELS], enzo or a data file (default enzo cosmo:1e7 cosmo:1e8)")
    p.add_argument("--truth-spp", type=int, default=2048, help="--resample: samples per pixel of the truth")
    p.add_argument("--floor-spp", type=int, default=None, help="--resample: spp of a rival's floor (truth/2)")
    p.add_argument("--max-spp", type=int, default=512, help="--resample: the curves' highest spp")
    p.add_argument("--resolutions", type=int, nargs="+", default=[128, 256, 512, 1024],
                   help="--resample: dense resolutions (voxels along the longest side)")
    p.add_argument("--resample-methods", nargs="+", default=["box"], help="--resample: box and/or nearest")
    p.add_argument("--renderers", nargs="+", default=["heterogeneous", "dense16"],
                   help="--resample: renderers of the dense rivals")
    p.add_argument("--check-max", type=int, default=512,
                   help="--resample: check the finest nearest resample against the truth up to this resolution")
    p.add_argument("--resample-memory", type=float, default=None,
                   help="--resample: GiB a rival may use (default 80%% of the memory available at start)")
    p.add_argument("--unfrozen", action="store_true", help="--resample: time plain mi.render frames")
    p.add_argument("--zoom", type=float, default=None, metavar="WIDTH",
                   help="--resample: a telephoto view of the densest cell whose field of view spans WIDTH of "
                        "the domain (e.g. 0.05: what a scientist looking at one halo sees); default the whole "
                        "domain")


def view_options(p):
    p.add_argument("--view", metavar="DATA", default=None,
                   help="how interactive mi-amr view is on DATA, measured in the page (chromium): frames/s "
                        "while dragging, change-to-frame and change-to-denoised times (--res, --repeats)")
    p.add_argument("--view-field", default=None, help="field of --view's data")
    p.add_argument("--view-preview-scale", type=float, default=0.5, help="--view: the viewer's preview scale")
    p.add_argument("--widget", metavar="DATA", default=None,
                   help="the notebook widget (sc.show()) on DATA in JupyterLab (chromium): frames/s reaching the "
                        "page through Jupyter's comm channel while orbiting (--res, --repeats, --view-field)")
    p.add_argument("--widget-seconds", type=float, default=4.0, help="--widget: each drag's length, seconds")


def modes_options(p):
    p.add_argument("--march", action="store_true",
                   help="the paper's comparison: ray_march (gradient shading) frames/s and time to 2%% of its "
                        "converged picture against multi's 1-spp convergence frames (mi_amr.bench.march)")
    p.add_argument("--march-cells", type=float, nargs="*", default=[1e7, 1e8], metavar="CELLS",
                   help="--march: block-structured data sets of these sizes (default 1e7 1e8)")
    p.add_argument("--march-res", type=int, default=512, help="--march: frame width and height (default 512)")
    p.add_argument("--march-multi-spp", type=int, default=8,
                   help="--march: spp of the two multi pictures whose difference estimates its error (8)")
    p.add_argument("--modes", action="store_true",
                   help="frames/s of amrvolpath's lighting modes beside the empty-medium frame (--res, 1 spp "
                        "unless --spp; --datasets x --tfs, then --modes-cells), and the uniform field against "
                        "Mitsuba's homogeneous medium (docs/performance/modes.md)")
    p.add_argument("--modes-cells", type=float, nargs="*", default=[1e7, 1e8], metavar="CELLS",
                   help="--modes: large data sets after the protocol's (octree-like cloud up to 1e7 cells, "
                        "block-structured above; files in --data-dir); default 1e7 1e8")
    p.add_argument("--modes-floor", action=argparse.BooleanOptionalAction, default=True,
                   help="--modes: time the uniform field against homogeneous (default)")
    p.add_argument("--modes-frames", type=int, default=5,
                   help="--modes: frames timed per pass, their median kept (default 5)")
    p.add_argument("--modes-figure", metavar="PNG", default=None,
                   help="--modes: also render scenes/demo.xml in the three modes side by side into PNG, with "
                        "each mode's 1-spp frame timed (the README's figure)")
    p.add_argument("--modes-figure-res", type=int, default=256, help="--modes-figure: each picture's size")
    p.add_argument("--modes-figure-spp", type=int, default=64, help="--modes-figure: samples per pixel")
    p.add_argument("--modes-bound", action="store_true",
                   help="what bounds the emission_absorption frame: its kernel split into the empty frame, the "
                        "walk and the look-ups, and two lower bounds (the cases of --modes; "
                        "docs/performance/modes.md section 1b)")
    p.add_argument("--modes-bound-res", type=int, default=256,
                   help="--modes-bound: the fine uniform grid whose look-ups bound the frame (256)")
    p.add_argument("--modes-bound-points", type=int, default=1 << 18,
                   help="--modes-bound: look-ups in the full-packet kernel that prices a look-up")
    p.add_argument("--modes-floor-res", type=int, default=128, help="--modes: frame size of the floor (128)")
    p.add_argument("--modes-floor-spp", type=int, default=16, help="--modes: samples per pixel of the floor (16)")


def grad_options(p):
    p.add_argument("--grad", action="store_true",
                   help="what a gradient step (render + dr.backward of an L2 loss, w.r.t. the cell values and "
                        "the TF) costs against the primal frame and Mitsuba's heterogeneous medium on a dense "
                        "grid, time and memory (docs/performance/gradients.md)")
    p.add_argument("--grad-data", nargs="+", default=["cloud:2e4:4", "cloud:1e6:3"], metavar="NAME:CELLS:LEVELS",
                   help="--grad: synthetic data sets (default cloud:2e4:4 cloud:1e6:3)")
    p.add_argument("--grad-integrators", nargs="+", default=["prbvolpath", "amrprbvolpath"],
                   help="--grad: differentiable integrators of the amr rows; one that does not load is skipped "
                        "(default prbvolpath amrprbvolpath)")
    p.add_argument("--grad-tf", default="spiky", help="--grad: TF preset (default spiky)")
    p.add_argument("--grad-res", type=int, default=128, help="--grad: frame width and height (default 128)")
    p.add_argument("--grad-spp", type=int, default=4, help="--grad: samples per pixel (default 4)")
    p.add_argument("--grad-steps", type=int, default=3,
                   help="--grad: steps timed per pass, their median kept (default 3)")
    p.add_argument("--grad-memory", action=argparse.BooleanOptionalAction, default=True,
                   help="--grad: one untimed step per pass for the peak memory (default)")


def vs_yt_options(p):
    p.add_argument("--vs-yt", nargs="*", default=None, metavar="DATA",
                   help="yt's volume renderer against amrvolpath's ray_march and emission_absorption on the "
                        "same AMR data and camera: each one's RMSE against the exact emission-absorption "
                        "integral, our time to yt's error (docs/performance/vs-yt.md). DATA: blocks, cells "
                        "(the bench's own data; the default: both), enzo-example (written under --out) or "
                        "any output yt loads (its field: --field, default density)")
    p.add_argument("--vs-yt-res", type=int, nargs="+", default=[128, 256, 512],
                   help="--vs-yt: image sizes (the 'cells' data: the first only)")
    p.add_argument("--vs-yt-n0", type=int, default=32, help="--vs-yt: level-0 cells per side (32)")
    p.add_argument("--vs-yt-cap", type=int, default=1024,
                   help="--vs-yt: emission_absorption's highest spp at 128^2, scaled by (128/size)^2 beyond "
                        "(1024)")
    p.add_argument("--vs-yt-march-cap", type=int, default=16, help="--vs-yt: ray_march's highest spp (16)")
    p.add_argument("--vs-yt-sampler", default="centres", choices=["centres", "multijitter", "stratified",
                                                                  "independent"],
                   help="--vs-yt: ray_march's pixel samples (centres: stratified without jitter, 1 spp is "
                        "the pixel centre as yt's ray)")
    p.add_argument("--vs-yt-sub", type=int, default=4,
                   help="--vs-yt: reference rays per pixel side (the box filter's footprint, 4)")
    p.add_argument("--vs-yt-cache", default=None,
                   help="--vs-yt: folder of the exact references (default OUT/reference-cache)")
    p.add_argument("--vs-yt-rounds", type=int, default=3, help="--vs-yt: alternated rounds (3)")
    p.add_argument("--vs-yt-samples", type=int, default=None,
                   help="--vs-yt: yt's num_samples per cell (default: yt's, 10)")


def adaptive_options(p):
    p.add_argument("--adaptive", nargs="*", default=None, metavar="DATA",
                   help="seconds to a picture within 2%% RMSE of converged: fixed spp against adaptive sampling, "
                        "raw against denoised, and the default command's whole process beside yt's "
                        "(docs/performance/adaptive.md). DATA: enzo, blocks, 1e7 (default: all)")
    p.add_argument("--adaptive-res", type=int, default=512, help="--adaptive: image size (512)")
    p.add_argument("--adaptive-ref-spp", type=int, default=512,
                   help="--adaptive: samples per pixel of each half of the reference (512; cached under --out)")
    p.add_argument("--rounds-adaptive", type=int, default=3,
                   help="--adaptive: whole-process rounds, ours and yt's alternated (3; 0: none)")


def iso_options(p):
    p.add_argument("--iso", action="store_true",
                   help="isosurfaces against yt's ds.surface on an analytic radial field over 2 and 3 levels: "
                        "cracks at level boundaries and hit errors against the exact sphere, the pictures side "
                        "by side, and frames/s of an isosurface picture (docs/performance/iso.md)")
    p.add_argument("--iso-levels", type=int, nargs="+", default=[2, 3], help="--iso: level counts (2 3)")
    p.add_argument("--iso-crack-res", type=int, default=512,
                   help="--iso: camera rays per side of the crack figures (512)")
    p.add_argument("--iso-yt-only", action="store_true", help="--iso: yt's surface only (no mi-amr rows)")
    p.add_argument("--iso-picture", default=None, metavar="PNG",
                   help="--iso: the side-by-side figure (default OUT/iso-vs-yt.png; none: no figure)")
    p.add_argument("--iso-picture-res", type=int, default=256, help="--iso: each panel's size (256)")
    p.add_argument("--iso-picture-spp", type=int, default=64, help="--iso: the pictures' samples per pixel (64)")
    p.add_argument("--iso-cells", type=float, nargs="*", default=[1e7, 1e8], metavar="CELLS",
                   help="--iso: block-structured data sets of the frame rate (files in --data-dir; default "
                        "1e7 1e8; none: no frame rate)")
    p.add_argument("--iso-res", type=int, default=512, help="--iso: the timed frame's width and height (512)")


def distributed_options(p):
    p.add_argument("--distributed", action="store_true",
                   help="speed-up of a Dask LocalCluster over one process (256x256, 256 spp unless "
                        "--res/--spp are given)")
    p.add_argument("--workers", type=int, default=2, help="workers of --distributed")
    p.add_argument("--chunk-spp", type=int, default=32, help="samples per chunk of --distributed")
    p.add_argument("--dist-scene", default="scenes/demo.xml", help="scene of --distributed")


if __name__ == "__main__":
    main()
