"""The lighting modes of ``amrvolpath`` (``mode``: docs/design.md section
6d) against analytic answers and brute-force random walks, for every
traversal.

The scenes are those of tests/test_emission.py: a distant camera looks down
the z axis of the unit cube through a narrow field of view, so every
pixel's ray crosses the medium over the same length 1 (within 2.2e-4), here
under a constant environment. A Monte Carlo mean is compared per channel
with its expectation within five standard errors estimated from the pixels
(all pixels share one expectation). Kernels are few: one per mode and
traversal, plus one with an HG phase function and one that glows.
"""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_amr import AMRCells, TransferFunction, distributed
from mi_amr.data.io import write_exabricks
from mi_amr.images import read_exr
from mi_amr.params import ParameterError, plugin_error
from mi_amr.plugins.integrator import MODES, integrator_class
from mi_amr.tools.cli import main

from conftest import cloud_scene_xml
from test_emission import FOV, flat_tf, mean_and_error, ortho_scene, two_level_cells

#: The constant environment, and the albedo of the slab's one colour.
ENV = np.array([0.6, 0.7, 0.9])
ALBEDO = np.array([0.8, 0.5, 0.2])
#: (traversal, sampling): every traversal, with a sampling it goes with.
TRAVERSALS = [("grid", "hash"), ("abr", "abr"), ("brick", "brick"), ("kdtree", "hash")]


def lit_scene(medium, mode, res=16, env=ENV, **integrator):
    """`ortho_scene` under a constant environment of radiance ``env``."""
    scene = ortho_scene(medium, res=res, mode=mode, **integrator)
    scene["env"] = {"type": "constant", "radiance": {"type": "rgb", "value": list(map(float, env))}}
    return scene


def uniform_two_level(value=0.5):
    """The two-level cells of tests/test_emission.py, all of one value: a
    homogeneous slab that the traversals still cut at the level change."""
    cells = two_level_cells()
    return AMRCells(cells.pos, cells.level, np.full(len(cells), value))


def slab(traversal, sampling, sigma, albedo=ALBEDO, **extra):
    return dict({"type": "amr", "data": uniform_two_level(), "transfer_function": flat_tf(albedo, 1.0),
                 "density_scale": sigma, "reconstruction": "nearest", "traversal": traversal,
                 "sampling": sampling}, **extra)


def check(mean, err, expected, tol_extra=0.0):
    tol = 5 * np.sqrt(err ** 2 + tol_extra ** 2) + 1e-4
    assert np.all(np.abs(mean - expected) < tol), (mean, expected, tol)


def single_scattering_walk(sigma, albedo, env, g=0.0, n=400_000, seed=1):
    """Brute force, independent of the renderer: analog particles entering
    the unit cube at z = 0 (x, y uniform in [0.2, 0.8]) along +z through a
    homogeneous medium of extinction ``sigma`` under a constant environment
    ``env``. A particle that leaves without colliding scores ``env``; at its
    first collision it takes a uniform direction w, weighted by albedo and
    ``4 pi p(w)`` (Henyey-Greenstein with ``g`` about +z), and flies again:
    if it leaves the cube without a second collision it scores that weight
    times ``env``, else 0 (single scattering). Returns per-channel (mean,
    standard error)."""
    rng = np.random.default_rng(seed)
    p = np.column_stack([rng.uniform(0.2, 0.8, n), rng.uniform(0.2, 0.8, n), rng.exponential(1.0 / sigma, n)])
    collided = p[:, 2] <= 1.0
    score = np.where(collided, 0.0, 1.0)
    i = np.nonzero(collided)[0]
    z = rng.uniform(-1, 1, len(i))
    phi = rng.uniform(0, 2 * np.pi, len(i))
    r = np.sqrt(1 - z * z)
    w = np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
    hg = (1 - g * g) / (1 + g * g - 2 * g * z) ** 1.5          # 4 pi p(w), cos theta = w . (+z)
    q = p[i] + w * rng.exponential(1.0 / sigma, len(i))[:, None]
    escaped = ~np.all((q >= 0) & (q <= 1), axis=1)
    light = np.zeros(n)
    light[i] = np.where(escaped, hg, 0.0)
    samples = score[:, None] * env + light[:, None] * (np.asarray(albedo) * env)
    return samples.mean(axis=0), samples.std(axis=0, ddof=1) / np.sqrt(n)


@pytest.mark.parametrize("traversal,sampling", TRAVERSALS)
def test01_emission_absorption_slab(llvm, traversal, sampling):
    """emission_absorption on a homogeneous slab of optical depth tau under
    a constant environment L: the first real collision scores the albedo
    (the TF colour, brightness 1) whatever the environment, a ray that
    escapes sees L: albedo (1 - e^-tau) + L e^-tau."""
    sigma = 1.3
    scene = mi.load_dict(lit_scene(slab(traversal, sampling, sigma), "emission_absorption"))
    mean, err = mean_and_error(mi.render(scene, spp=32, seed=3))
    expected = ALBEDO * (1 - np.exp(-sigma)) + ENV * np.exp(-sigma)
    check(mean, err, expected)
    assert err.max() < 0.005                 # tight enough to tell the environment's colour on the albedo


@pytest.mark.parametrize("traversal,sampling", TRAVERSALS)
def test02_emission_absorption_two_level_field_that_glows(llvm, traversal, sampling):
    """emission_absorption on the two-level field (values 0.25 then 0.75
    along the ray, alpha = value, colour and albedo linear in the value),
    glowing from a second field (temperature 2 then 6): along z the ray
    crosses tau_a = s 0.25 / 2 then tau_b = s 0.75 / 2, so
    L = [a_a + (1 - a_a) E_a](1 - e^-tau_a)
        + e^-tau_a [a_b + (1 - a_b) E_b](1 - e^-tau_b) + e^-(tau_a + tau_b) L."""
    s = 3.0
    c0, c1 = np.array([0.9, 0.5, 0.1]), np.array([0.3, 0.6, 0.9])
    extinction = TransferFunction([[*c0, 0.0], [*c1, 1.0]], (0.0, 1.0))
    emission = TransferFunction([[1, 0, 0, 1], [0, 0, 1, 1]], (0.0, 8.0))          # red at 0 -> blue at 8
    medium = {"type": "amr", "data": two_level_cells(), "transfer_function": extinction, "density_scale": s,
              "reconstruction": "nearest", "traversal": traversal, "sampling": sampling,
              "emission": emission, "emission_field": "temperature"}
    scene = mi.load_dict(lit_scene(medium, "emission_absorption"))
    mean, err = mean_and_error(mi.render(scene, spp=32, seed=5))
    albedo = lambda v: c0 + v * (c1 - c0)                                           # noqa: E731
    le = lambda t: np.array([1 - t / 8, 0.0, t / 8])                                # noqa: E731
    tau_a, tau_b = s * 0.25 / 2, s * 0.75 / 2
    a, b = albedo(0.25), albedo(0.75)
    expected = ((a + (1 - a) * le(2.0)) * (1 - np.exp(-tau_a))
                + np.exp(-tau_a) * (b + (1 - b) * le(6.0)) * (1 - np.exp(-tau_b))
                + np.exp(-tau_a - tau_b) * ENV)
    check(mean, err, expected)


def test03_emission_absorption_brightness_scales_the_colour(llvm):
    """No environment emitter, ``brightness`` 2.5: an escaping ray sees
    black, a collision 2.5 albedo: 2.5 albedo (1 - e^-tau). A negative
    brightness is refused in one line."""
    sigma = 1.3
    scene = mi.load_dict(ortho_scene(slab("grid", "hash", sigma), mode="emission_absorption", brightness=2.5))
    mean, err = mean_and_error(mi.render(scene, spp=32, seed=4))
    check(mean, err, 2.5 * ALBEDO * (1 - np.exp(-sigma)))
    with pytest.raises(Exception, match="brightness") as e:
        mi.load_dict(ortho_scene(slab("grid", "hash", sigma), mode="emission_absorption", brightness=-1.0))
    assert "\n" not in plugin_error(str(e.value)) and "brightness must be >= 0" in plugin_error(str(e.value))


@pytest.mark.parametrize("traversal,sampling", TRAVERSALS)
def test04_single_scattering_matches_a_one_bounce_walk(llvm, traversal, sampling):
    """single on a homogeneous slab (tau 1.5, isotropic phase) under a
    constant environment, against `single_scattering_walk`: one shadow ray
    with ratio tracking, the phase function's value, no MIS, then stop."""
    sigma = 1.5
    scene = mi.load_dict(lit_scene(slab(traversal, sampling, sigma), "single"))
    mean, err = mean_and_error(mi.render(scene, spp=64, seed=7))
    walk, walk_err = single_scattering_walk(sigma, ALBEDO, ENV)
    check(mean, err, walk, walk_err)
    # one bounce is less than the emission-absorption answer (the light
    # of half the directions crosses more medium) and more than the
    # unscattered light alone
    assert np.all(mean > ENV * np.exp(-sigma) + 0.05)


def test05_single_scattering_with_hg_phase_and_glow(llvm):
    """single with a forward HG phase function (g 0.6, its value in the
    light's direction matters) and a glowing medium (emission adds at the
    collision: (1 - albedo) E (1 - e^-tau) in expectation)."""
    sigma, g, glow = 1.5, 0.6, np.array([1.0, 0.5, 0.25])
    medium = slab("grid", "hash", sigma, phase={"type": "hg", "g": g}, emission=flat_tf(glow, 1.0))
    scene = mi.load_dict(lit_scene(medium, "single"))
    mean, err = mean_and_error(mi.render(scene, spp=64, seed=8))
    walk, walk_err = single_scattering_walk(sigma, ALBEDO, ENV, g=g)
    expected = walk + (1 - ALBEDO) * glow * (1 - np.exp(-sigma))
    check(mean, err, expected, walk_err)
    isotropic, _ = single_scattering_walk(sigma, ALBEDO, ENV, g=0.0)
    assert np.abs(walk - isotropic).max() > 10 * walk_err.max()          # the phase function shows


def test06_multi_is_the_default_estimator(llvm):
    """mode="multi" is the estimator without a mode: the same kernel and
    the very same image for the same seed; and it differs from single."""
    medium = slab("grid", "hash", 1.5)
    default = np.array(mi.render(mi.load_dict(lit_scene(medium, "multi")), spp=8, seed=2))
    scene = lit_scene(medium, "multi")
    del scene["integrator"]["mode"]
    unset = np.array(mi.render(mi.load_dict(scene), spp=8, seed=2))
    assert np.array_equal(default, unset)
    assert mi.load_dict({"type": "amrvolpath"}).mode == "multi"


def test07_mode_values_are_checked_and_volpath_has_none(llvm):
    """An unknown mode is refused with one line naming the allowed values;
    the XML string parameter is read; stock volpath takes no mode."""
    cls = integrator_class()
    props = mi.Properties("amrvolpath")
    props["mode"] = "pathtracer"
    with pytest.raises(ParameterError) as info:
        cls(props)
    message = str(info.value)
    assert "\n" not in message and "'pathtracer'" in message
    assert all(m in message for m in MODES)
    with pytest.raises(Exception) as info:
        mi.load_dict({"type": "amrvolpath", "mode": "Single"})
    line = plugin_error(str(info.value))
    assert "\n" not in line and "unknown mode 'Single'" in line and all(m in line for m in MODES)
    for m in MODES:
        xml = f'<integrator version="3.0.0" type="amrvolpath"><string name="mode" value="{m}"/></integrator>'
        assert mi.load_string(xml).mode == m
    with pytest.raises(Exception, match="mode"):
        mi.load_dict({"type": "volpath", "mode": "single"})


def test08_modes_follow_tf_changes_without_recompiling(llvm):
    """The mode is fixed at construction; a TF change (through
    ``params.update()``) compiles nothing in a frozen render, in each of
    the cheap modes, and the new image has the new albedo."""
    for mode in ("emission_absorption", "single"):
        scene = mi.load_dict(lit_scene(slab("grid", "hash", 1.3), mode, res=8))
        params = mi.traverse(scene)
        key = next(k for k in params.keys() if k.endswith("tf_rgba"))

        @dr.freeze
        def render(scene, seed):
            return mi.render(scene, spp=4, seed=seed)

        for seed in (1, 2, 3):
            render(scene, dr.opaque(mi.UInt32, seed))
        recordings = render.n_recordings
        params[key] = mi.Float(np.tile([0.1, 0.9, 0.4, 1.0], 2))
        params.update()
        got = np.array(render(scene, dr.opaque(mi.UInt32, 3)))
        assert render.n_recordings == recordings, mode
        np.testing.assert_allclose(got, np.array(mi.render(scene, spp=4, seed=3)), rtol=1e-4, atol=1e-5)


def test09_emission_absorption_is_the_same_colour_under_any_sky(llvm):
    """A dense cube (optical depth 60 across) under a ``sunsky`` (dark below
    the horizon) and an environment map: seen from above and from below,
    through the sky and towards the ground, every pixel is the TF colour
    times the brightness (every path collides: no variance), as sci-vis
    renderers show it; the old definition (the albedo times the sky along
    the ray) painted the view from above black."""
    T = mi.ScalarTransform4f
    texels = np.tile(np.array([[0.2, 0.9, 0.4], [0.9, 0.1, 0.1]], np.float32)[:, None], (1, 8, 1))
    skies = {"sunsky": {"type": "sunsky", "sun_direction": [0.5, 0.6, 0.9]},
             "envmap": {"type": "envmap", "bitmap": mi.Bitmap(texels)}}
    for name, sky in skies.items():
        for z in (3.0, -2.0):                        # above, looking down; below, looking up
            d = ortho_scene(slab("grid", "hash", 60.0), mode="emission_absorption", brightness=0.8)
            d["sensor"]["to_world"] = T().look_at([0.5, 0.5, z], [0.5, 0.5, 0.5], [0, 1, 0])
            d["sensor"]["fov"] = 10.0
            d["sky"] = sky
            img = np.array(mi.render(mi.load_dict(d), spp=8, seed=2), np.float64).reshape(-1, 3)
            np.testing.assert_allclose(img, np.tile(0.8 * ALBEDO, (len(img), 1)), rtol=1e-4, atol=1e-4,
                                       err_msg=f"{name}, camera at z = {z}")


def amrvolpath_xml(folder, mode_line=""):
    """A small XML scene (16x16, 4 spp) with the amrvolpath integrator and a
    slab under a constant environment; the data file is named relative to
    the scene (a rewritten scene must still find it)."""
    write_exabricks(uniform_two_level(), folder / "d.cells")
    (folder / "s.xml").write_text(f"""<scene version="3.0.0">
    <default name="spp" value="4"/>
    <integrator type="amrvolpath"><integer name="max_depth" value="16"/>{mode_line}</integrator>
    <sensor type="perspective"><float name="fov" value="{FOV}"/>
        <transform name="to_world"><lookat origin="0.5, 0.5, -20" target="0.5, 0.5, 0.5" up="0, 1, 0"/></transform>
        <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
        <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/>
            <rfilter type="box"/></film>
    </sensor>
    <emitter type="constant"><rgb name="radiance" value="0.6, 0.7, 0.9"/></emitter>
    <medium type="amr" id="m"><string name="filename" value="d.cells"/>
        <string name="transfer_function" value="foggy"/><float name="density_scale" value="3"/>
        <string name="reconstruction" value="nearest"/></medium>
    <shape type="cube"><transform name="to_world"><scale value="0.5"/><translate value="0.5, 0.5, 0.5"/></transform>
        <bsdf type="null"/><ref name="interior" id="m"/></shape>
</scene>""")
    return folder / "s.xml"


def test10_render_mode_flag_on_an_xml_scene(llvm, tmp_path, capsys):
    """``mi-amr render --mode`` renders an XML scene as if its amrvolpath
    integrator named the mode (the same image, seed for seed), here and in
    a cluster worker's loader; a scene with another integrator is refused
    in one line."""
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    plain = amrvolpath_xml(tmp_path / "a")
    written = amrvolpath_xml(tmp_path / "b", '<string name="mode" value="emission_absorption"/>')
    assert main(["render", str(plain), "-o", str(tmp_path / "ea.exr"), "--mode", "emission_absorption",
                 "--no-adaptive", "-q"]) == 0
    assert main(["render", str(plain), "-o", str(tmp_path / "multi.exr"), "-q"]) == 0
    got, multi = read_exr(tmp_path / "ea.exr"), read_exr(tmp_path / "multi.exr")
    want = np.array(distributed.render_local(written, 4, chunk_spp=1))         # the command's chunks
    assert np.array_equal(got, want[..., :got.shape[-1]])
    want = np.array(distributed.render_local(written, 4))                      # one chunk
    assert np.abs(got - multi).max() > 0.02                      # the mode changed the image
    spec = distributed.scene_spec(plain, integrator={"mode": "emission_absorption"})
    chunk = distributed.render_chunk(spec, 4, distributed.chunk_seeds(0, 1)[0])
    distributed.forget_scene(spec)
    np.testing.assert_allclose(chunk[..., :3] / chunk[..., -1:], want[..., :3], rtol=1e-5, atol=1e-6)
    capsys.readouterr()
    cloud = cloud_scene_xml(tmp_path, data=uniform_two_level())          # stock volpath
    assert main(["render", str(cloud), "-o", str(tmp_path / "c.exr"), "--mode", "single", "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "amrvolpath" in err and "'volpath'" in err, err


def test11_render_mode_flag_on_data_keeps_the_mode_in_its_scene(llvm, tmp_path):
    """Data rendered with ``--mode`` write an OUT.xml whose integrator names
    the mode: re-rendering that file gives the same image."""
    write_exabricks(uniform_two_level(), tmp_path / "d.cells")
    args = ["--res", "16", "--spp", "4", "-q"]
    assert main(["render", str(tmp_path / "d.cells"), "-o", str(tmp_path / "out.exr"), "--mode", "single",
                 *args]) == 0
    assert 'name="mode" value="single"' in (tmp_path / "out.xml").read_text()
    assert main(["render", str(tmp_path / "out.xml"), "-o", str(tmp_path / "again.exr"), *args]) == 0
    np.testing.assert_allclose(read_exr(tmp_path / "out.exr"), read_exr(tmp_path / "again.exr"),
                               rtol=1e-5, atol=1e-6)
