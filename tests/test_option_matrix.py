"""Every documented option renders: the option matrix of the ``amr`` medium
and of the three integrators that render it (stock ``volpath``,
``amrvolpath``, ``amrprbvolpath``; issue 50).

The options and their values come from the parsers themselves, not from a
copied list: each parameter a plugin knows (its ``KNOWN``) is given a value
it cannot take, and the one-line refusal says what it takes ("unknown
traversal 'x' (choose from grid, abr, brick, kdtree)", "must be true or
false", "must be >= 1"). A new option or value is in the matrix without an
edit here. Each combination must render finite, non-negative pixels, and
its image mean must agree with the default configuration's (`amrvolpath`,
the same value of every option that changes the picture, `PICTURE`) within
Monte Carlo error: passes of independent seeds, z-scores of the difference
of means from their sample variances (`mi_amr.testing.block_z_scores`, one
8x8 block), below `Z_MAX`.

The default run takes every value of every medium option once against the
defaults in stock volpath and amrvolpath, every value of every integrator
option in its integrator, and every (traversal, sampling) pair in those two
integrators (those two decide which structures are built, and stock
volpath's warning once asked for one that was not). The medium options and
the pairs in amrprbvolpath (test02b, test03b) are ``slow``: its primal calls
the same medium methods as amrvolpath, and each case is a kernel of its own
(about 0.2 s cold, compiling dominates a case). The full cross product
traversal x sampling x reconstruction x majorant x integrator and mode is
``slow``. One data set (two levels, 225 cells), 8x8 pixels: a distinct
kernel costs a fraction of a second cold, and a pass about 10 ms, at 4 spp
as at 32 (tracing the frame dominates: each case's passes replay one
``dr.freeze`` recording, `render_passes`, 28 -> 21 s cold for test02), so passes take 32 spp: a majorant
5x too low in stock volpath's ``majorant=global`` moves the mean by 10
standard errors there, 4 at 4 spp.
"""

import re

import mitsuba as mi
import numpy as np
import pytest

import mi_amr.plugins.medium as medium_module
from mi_amr.params import plugin_error
from mi_amr.plugins import integrator as amrvolpath_module
from mi_amr.plugins import prb_integrator as prb_module
from mi_amr.plugins.options import KNOWN as MEDIUM_KNOWN
from mi_amr.testing import block_z_scores, render_passes

from conftest import random_amr, volume_scene

#: The integrators that render an ``amr`` medium, with the parameters each
#: knows (stock volpath: none of ours).
INTEGRATORS = {"volpath": set(), "amrvolpath": amrvolpath_module.KNOWN, "amrprbvolpath": prb_module.KNOWN}
#: The axes of the full (slow) cross product; their values come from the parsers.
AXES = ("traversal", "sampling", "reconstruction", "majorant")
#: Options that change the expected picture (the reference renders them as
#: the case gives them); every other option must leave the image's
#: expectation alone. An ``emission*`` option glows: stock volpath has no
#: medium emission, so those cases are compared in our integrators only;
#: ``iso_only`` (given an iso value, `ISO`) likewise: stock volpath cannot
#: see isosurfaces (docs/manual/isosurfaces.md).
PICTURE = {"reconstruction", "value_transform", "mode", "brightness", "hide_emitters", "max_iterations", "density_scale",
           "tf_min", "tf_max", "emission_min", "emission_max", "emission_scale", "emission_transform",
           "emission_model", "iso_only"}
#: The iso value (the data's units) of the ``iso_only`` cases (refused without one).
ISO = 0.5
#: Options whose picture also depends on the integrator's own loops (a ray
#: that meets ``max_iterations`` stops where that integrator's loop is): the
#: reference renders in the case's integrator.
OWN_REFERENCE = {"max_iterations"}
#: A value no option takes (strings), and numbers below every minimum.
NOT_A_VALUE = "no-such-value"
BELOW_INT, BELOW_FLOAT = -2 ** 40, -1e300
#: The base medium: foggy TF, optical depth of a few across the cube.
BASE = {"type": "amr", "transfer_function": "foggy", "density_scale": 20.0}
RES, SPP, PASSES, REF_PASSES = 8, 32, 8, 16
#: |z| bound of a mean's difference: with 8 and 16 passes (Welch, about 15
#: degrees of freedom) P(|t| > 6) is about 3e-5 per comparison, 3e-3 over
#: the default run's hundred comparisons; seeds are fixed, so a run repeats.
Z_MAX = 6.0


def glowing(med: dict) -> dict:
    """``med`` with an emission TF where it sets an ``emission*`` option
    (they are refused without one), except for the blackbody model, which
    glows without one (and refuses one)."""
    if med.get("emission_model") == "blackbody":
        return med
    return dict(med, emission="blackbody") if any(k.startswith("emission") for k in med) else med


@pytest.fixture(scope="module")
def cells():
    data = random_amr(seed=1, n=8, levels=2)
    assert len(np.unique(data.level)) == 2 and 100 <= len(data) <= 1000
    return data


def _refusal(load) -> str:
    """The one-line refusal of ``load()`` (Mitsuba's wrapper stripped), or ''."""
    try:
        load()
    except Exception as e:                     # noqa: BLE001 (Mitsuba wraps the plugin's error)
        return plugin_error(str(e))
    return ""


def _values(name: str, load) -> tuple:
    """The values option ``name`` takes, as its parser's refusals say:
    ``load(value)`` builds the plugin with that value. Choices and
    booleans: all (Mitsuba's base integrator types ``hide_emitters``
    itself); numbers: their minimum (an edge); other: none."""
    line = _refusal(lambda: load(NOT_A_VALUE))
    assert "\n" not in line and (not line or name in line), line
    m = re.search(rf"unknown {name} '{NOT_A_VALUE}' \(choose from (.*)\)", line)
    if m:
        return tuple(m.group(1).split(", "))
    if f"{name} must be true or false" in line or f'"{name}" has the wrong type (expected boolean' in line:
        return (False, True)
    for kind, below in (("an integer", BELOW_INT), ("a number", BELOW_FLOAT)):
        if f"{name} must be {kind}" in line:
            m = re.search(rf"{name} must be >= (\S+), got", _refusal(lambda: load(below)))
            if m:
                v = float(m.group(1))
                return (int(v),) if kind == "an integer" else (v,)
    return ()


class Matrix:
    """The options found by probing: ``medium[name]`` and
    ``integrator[plugin][name]`` -> values."""

    def __init__(self, cells):
        def medium(name):
            # with an emission TF, so that the emission options are parsed too
            return lambda v: mi.load_dict(dict(BASE, data=cells, emission="blackbody", **{name: v}))

        def integ(plugin, name):
            return lambda v: mi.load_dict({"type": plugin, name: v})

        self.medium = {n: v for n in sorted(MEDIUM_KNOWN) if (v := _values(n, medium(n)))}
        self.integrator = {p: {n: v for n in sorted(known) if (v := _values(n, integ(p, n)))}
                           for p, known in INTEGRATORS.items()}


@pytest.fixture(scope="module")
def matrix(variant, cells):
    return Matrix(cells)


class Renderer:
    """Renders cases ``(integrator, medium options, integrator options)``
    and compares them with their references (cached by key)."""

    def __init__(self, cells):
        self.cells, self.refs, self.failures, self.compared = cells, {}, [], 0

    def scene(self, integrator, med, integ):
        medium = dict(BASE, data=self.cells, **glowing(med))
        if med.get("iso_only"):
            medium["iso"] = ISO
        scene = volume_scene(medium, res=RES, integrator=integrator, max_depth=8)
        scene["integrator"].update(integ)
        medium_module._WARNED.clear()             # every once-per-process warning runs for every case
        return mi.load_dict(scene)

    def check(self, integrator, med=None, integ=None, compare=True):
        med, integ = dict(med or {}), dict(integ or {})
        case = f"{integrator} {med} {integ}"
        try:
            passes = render_passes(self.scene(integrator, med, integ), PASSES if compare else 1, SPP)
        except Exception as e:                 # noqa: BLE001
            while e.__cause__ is not None or e.__context__ is not None:     # Dr.Jit's wrapper: the cause
                e = e.__cause__ or e.__context__
            self.failures.append(f"{case}: {type(e).__name__}: {plugin_error(str(e))}")
            return
        if not (np.all(np.isfinite(passes)) and passes.min() >= 0.0):
            self.failures.append(f"{case}: pixels not finite and non-negative "
                                 f"(min {np.nanmin(passes)}, {np.sum(~np.isfinite(passes))} not finite)")
            return
        glows = any(k.startswith("emission") for k in med)
        if not compare or ((glows or med.get("iso_only")) and integrator == "volpath"):
            return                                # stock volpath sees neither glow nor isosurfaces
        ref_integrator = integrator if OWN_REFERENCE & set(med) else "amrvolpath"
        key = (ref_integrator,) + tuple(sorted((k, v) for k, v in {**med, **integ}.items() if k in PICTURE))
        if key not in self.refs:
            d = dict(key[1:])
            self.refs[key] = render_passes(
                self.scene(ref_integrator, {k: v for k, v in d.items() if k in MEDIUM_KNOWN},
                           {k: v for k, v in d.items() if k not in MEDIUM_KNOWN}), REF_PASSES, SPP, seed0=1000)
        z = float(block_z_scores(passes, self.refs[key], block=RES)[0, 0])
        self.compared += 1
        if not abs(z) < Z_MAX:
            self.failures.append(f"{case}: image mean {passes.mean():.5g} against the default's "
                                 f"{self.refs[key].mean():.5g}, z = {z:.3g}")

    def assert_ok(self):
        assert not self.failures, f"{len(self.failures)} cases failed:\n" + "\n".join(self.failures)


@pytest.fixture
def renderer(cells):
    saved = set(medium_module._WARNED)
    yield Renderer(cells)
    medium_module._WARNED.clear()
    medium_module._WARNED.update(saved)


def _integrator_modes(matrix):
    """``(integrator, {mode: m})`` for every integrator and each mode it takes."""
    for plugin in INTEGRATORS:
        for m in matrix.integrator[plugin].get("mode", (None,)):
            yield plugin, ({} if m is None else {"mode": m})


# ---- The probes: what the parsers say they take -------------------------------
def test01_the_parsers_name_every_axis_and_refuse_in_one_line(matrix, cells):
    """The probes find every axis of the matrix with at least two values
    (the tables the code chooses from: traversals, samplings,
    reconstruction methods, majorants, modes), and every refusal they met
    was one line naming the parameter (`_values`). A value outside an
    option's choices is refused in one line that names the option and its
    choices."""
    for axis in AXES:
        assert len(matrix.medium.get(axis, ())) >= 2, (axis, matrix.medium)
    assert set(matrix.integrator["amrvolpath"]["mode"]) == set(amrvolpath_module.MODES)
    from mi_amr.plugins.prb_integrator import REPLAYED_MODES
    assert set(matrix.integrator["amrprbvolpath"]["mode"]) == set(REPLAYED_MODES) == set(amrvolpath_module.MODES) - {
        "ray_march"}
    from mi_amr.building import SAMPLINGS, TRAVERSALS
    assert set(matrix.medium["traversal"]) == set(TRAVERSALS)
    assert set(matrix.medium["sampling"]) == set(SAMPLINGS)
    for name, values in matrix.medium.items():
        if isinstance(values[0], str):
            line = _refusal(lambda: mi.load_dict(dict(BASE, data=cells, **glowing({name: values[0].upper() + "x"}))))
            assert "\n" not in line and name in line and all(v in line for v in values), line


# ---- The default run ----------------------------------------------------------
@pytest.mark.slow      # 25 s of CPU cold; test03 (every traversal and sampling) stays default (slow since the session of issues 61/64: the default suite over its 5-minute budget on CI)
def test02_every_option_value_renders_against_the_defaults(matrix, renderer):
    """Every value of every medium option (its other options at their
    defaults) in stock volpath and amrvolpath (amrprbvolpath: test02b), and
    every value of every integrator option in its integrator, amrprbvolpath's
    included: finite, non-negative pixels whose mean agrees with the default
    configuration's within Monte Carlo error."""
    cases = _medium_cases(matrix, renderer, ("volpath", "amrvolpath"))
    for plugin, options in matrix.integrator.items():
        for name, values in options.items():
            for v in values:
                renderer.check(plugin, integ={name: v})
    renderer.assert_ok()
    assert renderer.compared >= 2 * len(cases) - 2      # the glowing and iso cases in volpath are not compared


@pytest.mark.slow
def test02b_every_medium_option_value_renders_in_amrprbvolpath(matrix, renderer):
    """test02's medium options in amrprbvolpath (its primal kernels call the
    same medium methods as amrvolpath's; 41 kernels, 8 s cold: slow to keep
    the default suite's time; test02 keeps amrprbvolpath's own options)."""
    cases = _medium_cases(matrix, renderer, ("amrprbvolpath",))
    renderer.assert_ok()
    assert renderer.compared == len(cases)


def _medium_cases(matrix, renderer, integrators) -> list:
    """Every value of every medium option in each of ``integrators``; the cases."""
    cases = [(name, v) for name, values in matrix.medium.items() for v in values]
    for name, v in cases:
        for plugin in integrators:
            renderer.check(plugin, {name: v})
    return cases


def test03_every_traversal_and_sampling_pair_renders_in_every_integrator(matrix, renderer):
    """The traversal and the sampling decide which structures are built:
    every pair in stock volpath and amrvolpath (amrprbvolpath: test03b) (stock volpath once crashed with
    ``traversal=abr, sampling=abr``: a warning asked for the macrocell grid,
    which neither builds), compared with the default's mean."""
    _pairs(matrix, renderer, ("volpath", "amrvolpath"))


@pytest.mark.slow
def test03b_every_traversal_and_sampling_pair_renders_in_amrprbvolpath(matrix, renderer):
    """test03 in amrprbvolpath (its primal kernels walk the same
    structures as amrvolpath's; slow to keep the default suite's time)."""
    _pairs(matrix, renderer, ("amrprbvolpath",))


def _pairs(matrix, renderer, integrators):
    for t in matrix.medium["traversal"]:
        for s in matrix.medium["sampling"]:
            for plugin in integrators:
                renderer.check(plugin, {"traversal": t, "sampling": s})
    renderer.assert_ok()


# ---- The full cross product (slow) -------------------------------------------
@pytest.mark.slow
def test04_the_full_cross_product_renders(matrix, renderer):
    """traversal x sampling x reconstruction x majorant x (integrator, mode):
    every combination renders and agrees with its default's mean."""
    import itertools
    for values in itertools.product(*(matrix.medium[a] for a in AXES)):
        for plugin, integ in _integrator_modes(matrix):
            renderer.check(plugin, dict(zip(AXES, values)), integ)
    renderer.assert_ok()


# ---- Documented refusals ------------------------------------------------------
def test05_documented_refusals_are_one_line_naming_the_parameter(variant, cells):
    """The refusals docs/manual/medium.md lists ("Refused combinations"):
    each is one line that names the offending parameter."""
    refusals = [
        ({"grid_refinement": 3}, "grid_refinement"),
        ({"tf_min": 2.0, "tf_max": 1.0}, "tf_min"),
        ({"memory_limit": 1.0}, "memory_limit"),
        ({"emission_transform": "log10"}, "emission"),
        ({"scalars": "x.scalars"}, "scalars"),
        ({"traversal": "octree"}, "traversal"),
    ]
    for extra, word in refusals:
        line = _refusal(lambda: mi.render(mi.load_dict(volume_scene(dict(BASE, data=cells, **extra), res=RES)),
                                          spp=1))
        assert line and "\n" not in line and word in line, (extra, line)
    for plugin in ("amrvolpath", "amrprbvolpath"):
        line = _refusal(lambda: mi.load_dict({"type": plugin, "mode": "Multi"}))
        assert line and "\n" not in line and "mode" in line, line
    line = _refusal(lambda: mi.load_dict({"type": "amrprbvolpath", "residual_ratio_tracking": True}))
    assert line and "\n" not in line and "residual_ratio_tracking" in line, line
