"""Glowing gas: emission in ``amrvolpath`` against analytic answers and a
brute-force random walk, on every traversal, with the minorant estimators,
in frozen frames and through emission changes without recompiling.

Every scene looks down the z axis of the unit cube from far away through a
narrow field of view, so each pixel's ray crosses the medium over the
same length 1 (within 2.2e-4); there are no other lights, so all the light is the medium's. A
Monte Carlo mean is compared with its expectation within five standard
errors estimated from the pixels (all pixels share one expectation).
"""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_amr import AMRCells, TransferFunction

#: A camera far down the z axis with a narrow field of view: its film covers
#: x, y in [0.2, 0.8] at z = 0, and every ray crosses the cube within 1.2
#: degrees of the axis, over a length within 2.2e-4 of 1 (far below the
#: tolerances). (Mitsuba's orthographic sensor cannot be frozen.)
DISTANCE = 20.0
FOV = float(np.degrees(2 * np.arctan(0.3 / DISTANCE)))


def ortho_scene(medium, res=16, max_depth=64, **integrator):
    """The medium in a unit cube seen along +z by a distant camera whose
    film covers x, y in [0.2, 0.8] (every ray crosses z = 0..1)."""
    T = mi.ScalarTransform4f
    return {"type": "scene",
            "integrator": dict({"type": "amrvolpath", "max_depth": max_depth}, **integrator),
            "sensor": {"type": "perspective", "fov": FOV,
                       "to_world": T().look_at([0.5, 0.5, -DISTANCE], [0.5, 0.5, 0.5], [0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}}},
            "cube": {"type": "cube", "to_world": T().translate([0.5, 0.5, 0.5]) @ T().scale(0.5),
                     "bsdf": {"type": "null"}, "interior": medium}}


def mean_and_error(image):
    """Per-channel image mean and its standard error (pixels are iid)."""
    px = np.asarray(image, dtype=np.float64).reshape(-1, 3)
    return px.mean(axis=0), px.std(axis=0, ddof=1) / np.sqrt(len(px))


def flat_tf(rgb, alpha, domain=(0.0, 1.0)):
    """One colour and one alpha for every value."""
    return TransferFunction(np.tile([*rgb, alpha], (2, 1)), domain)


def uniform_cells(n=4, value=0.5):
    """``n^3`` cells of one level filling their box, all of ``value``."""
    g = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return AMRCells(g, np.zeros(len(g), np.int32), np.full(len(g), value))


def two_level_cells():
    """Fine cells (level 0, value 0.25, temperature 2) fill z in [0, 4) of an
    8^3 box, coarse ones (level 1, value 0.75, temperature 6) z in [4, 8):
    along z a ray crosses half its length in each."""
    fine = np.stack(np.meshgrid(np.arange(8), np.arange(8), np.arange(4), indexing="ij"), -1).reshape(-1, 3)
    coarse = np.stack(np.meshgrid(np.arange(4), np.arange(4), np.arange(2, 4), indexing="ij"), -1).reshape(-1, 3) * 2
    pos = np.concatenate([fine, coarse])
    level = np.r_[np.zeros(len(fine)), np.ones(len(coarse))].astype(np.int32)
    value = np.r_[np.full(len(fine), 0.25), np.full(len(coarse), 0.75)]
    temperature = np.r_[np.full(len(fine), 2.0), np.full(len(coarse), 6.0)]
    return AMRCells(pos, level, value, fields={"temperature": temperature})


#: Absorbing, not scattering (albedo 0): what emission-absorption renderers draw.
BLACK = flat_tf((0.0, 0.0, 0.0), 1.0)
GLOW = np.array([1.0, 0.5, 0.25])


@pytest.mark.parametrize("decomposition", [False, True])
def test01_constant_slab_without_scattering(llvm, decomposition):
    """L = L_e (1 - exp(-sigma_a d)) for a constant slab of depth d = 1
    (plain delta tracking, and decomposition tracking, which on a constant
    field finds every collision through its minorant without a look-up)."""
    sigma, scale = 1.3, 2.0
    medium = {"type": "amr", "data": uniform_cells(), "transfer_function": BLACK, "density_scale": sigma,
              "reconstruction": "nearest", "emission": flat_tf(GLOW, 1.0), "emission_scale": scale}
    scene = mi.load_dict(ortho_scene(medium, decomposition_tracking=decomposition))
    assert scene.integrator().sample  # noqa: B018
    mean, err = mean_and_error(mi.render(scene, spp=64, seed=3))
    expected = scale * GLOW * (1.0 - np.exp(-sigma))
    assert np.all(np.abs(mean - expected) < 5 * err + 1e-4), (mean, expected, err)


@pytest.mark.parametrize("decomposition", [False, True])
def test01b_emission_of_the_extinction_field_from_the_collisions_value(llvm, decomposition):
    """An emission TF over the extinction field itself takes L_e from the
    value the free flight found at its real collision (one point query);
    a control collision of decomposition tracking, which looks nothing up,
    looks L_e up. Two halves along the ray (values 0.25 then 0.75, L_e
    proportional to the value, sigma constant): L = L_e1 (1 - e^{-s/2}) +
    e^{-s/2} L_e2 (1 - e^{-s/2})."""
    sigma, scale = 1.3, 2.0
    cells = two_level_cells()
    glow = TransferFunction(np.array([[*GLOW, 0.0], [*GLOW, 1.0]]), (0.0, 1.0))     # alpha = value
    medium = {"type": "amr", "data": AMRCells(cells.pos, cells.level, cells.value), "transfer_function": BLACK,
              "density_scale": sigma, "reconstruction": "nearest", "emission": glow, "emission_scale": scale}
    scene = mi.load_dict(ortho_scene(medium, decomposition_tracking=decomposition))
    mean, err = mean_and_error(mi.render(scene, spp=64, seed=5))
    half = np.exp(-sigma / 2)
    expected = scale * GLOW * (0.25 * (1 - half) + half * 0.75 * (1 - half))
    assert np.all(np.abs(mean - expected) < 5 * err + 1e-4), (mean, expected, err)


@pytest.mark.parametrize("traversal,sampling", [("grid", "hash"), ("abr", "abr"), ("brick", "brick"),
                                                ("kdtree", "hash")])
def test02_two_level_field_with_a_second_emission_field(llvm, traversal, sampling):
    """Extinction from ``value`` (alpha = value), emission from another
    field, ``temperature``, on the same two-level cells: along z the ray
    crosses optical depth tau_a = s 0.25 / 2 then tau_b = s 0.75 / 2, so
    L = L_a (1 - e^-tau_a) + e^-tau_a L_b (1 - e^-tau_b), with L_e read
    from the emission TF at each half's temperature."""
    s = 3.0
    extinction = TransferFunction([[0, 0, 0, 0], [0, 0, 0, 1]], (0.0, 1.0))        # alpha = value
    emission = TransferFunction([[1, 0, 0, 1], [0, 0, 1, 1]], (0.0, 8.0))          # red at 0 -> blue at 8
    medium = {"type": "amr", "data": two_level_cells(), "transfer_function": extinction, "density_scale": s,
              "reconstruction": "nearest", "traversal": traversal, "sampling": sampling,
              "emission": emission, "emission_field": "temperature"}
    scene = mi.load_dict(ortho_scene(medium))
    mean, err = mean_and_error(mi.render(scene, spp=64, seed=5))
    le = lambda t: np.array([1 - t / 8, 0.0, t / 8])                             # noqa: E731
    tau_a, tau_b = s * 0.25 / 2, s * 0.75 / 2
    expected = le(2.0) * (1 - np.exp(-tau_a)) + np.exp(-tau_a) * le(6.0) * (1 - np.exp(-tau_b))
    assert np.all(np.abs(mean - expected) < 5 * err + 1e-4), (mean, expected, err)


@pytest.mark.parametrize("reconstruction,sampling", [("tent", "hash"), ("tent", "brick"), ("nearest", "abr")])
def test02b_the_flights_one_look_up_carries_the_emission_field(llvm, reconstruction, sampling):
    """One point query per collision (docs/design.md section 12): the free
    flight's look-up reconstructs the emission field too. At every real
    collision the ``carried`` value equals the brute-force reconstruction of
    that field at the collision point (1e-4 relative: float32 weights), and
    ``value`` that of the extinction field, for each method and sampling."""
    from mi_amr.testing import brute_force
    rng = np.random.default_rng(4)
    base = two_level_cells()
    value = rng.uniform(0.2, 1.0, len(base))
    temperature = rng.uniform(1.0, 8.0, len(base))
    cells = AMRCells(base.pos, base.level, value, fields={"temperature": temperature})
    medium = mi.load_dict({"type": "amr", "data": cells, "density_scale": 3.0,
                           "transfer_function": TransferFunction([[0, 0, 0, 0], [0, 0, 0, 1]], (0.0, 1.0)),
                           "reconstruction": reconstruction, "sampling": sampling,
                           "emission": TransferFunction([[1, 0, 0, 1], [0, 0, 1, 1]], (0.0, 8.0)),
                           "emission_field": "temperature"})
    n = 2048
    o = np.column_stack([rng.uniform(0.05, 0.95, (n, 2)), np.full(n, -1.0)]).astype(np.float32)
    d = rng.normal(size=(n, 3)) * [0.2, 0.2, 0.0] + [0.0, 0.0, 1.0]
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(1, n)
    ray = mi.Ray3f(mi.Point3f(o.T), mi.Vector3f(d.T))
    flight = medium.free_flight(ray, mi.Float(np.inf), sampler, mi.Bool(True))
    looked = flight.looked.numpy()
    assert looked.sum() > n // 2
    t = flight.t.numpy()[looked]
    p = o[looked] + t[:, None] * d[looked]                  # world = local: the unit cube
    lo, hi = medium.structures.volume.bounds
    x = lo + p * (np.asarray(hi) - np.asarray(lo))          # absolute finest units
    for got, field in ((flight.carried, temperature), (flight.value, value)):
        want, found = brute_force(AMRCells(base.pos, base.level, field), x, reconstruction)
        assert found.all()
        np.testing.assert_allclose(got.numpy()[looked], want, rtol=1e-4)


def random_walk_radiance(sigma, albedo, le, n=400_000, seed=1):
    """Brute force, independent of the renderer: analog random walks of
    ``n`` particles entering the unit cube at z = 0 (x, y uniform in [0.2,
    0.8]) along +z through a homogeneous medium with isotropic scattering;
    at each collision a particle is absorbed with probability 1 - albedo and
    then scores ``le``; leaving the cube scores 0. Returns (mean, standard
    error)."""
    rng = np.random.default_rng(seed)
    p = np.column_stack([rng.uniform(0.2, 0.8, n), rng.uniform(0.2, 0.8, n), np.zeros(n)])
    d = np.tile([0.0, 0.0, 1.0], (n, 1))
    score = np.zeros(n)
    alive = np.ones(n, bool)
    while alive.any():
        i = np.nonzero(alive)[0]
        p[i] += d[i] * rng.exponential(1.0 / sigma, len(i))[:, None]
        inside = np.all((p[i] >= 0) & (p[i] <= 1), axis=1)
        alive[i[~inside]] = False
        i = i[inside]
        absorbed = rng.uniform(size=len(i)) >= albedo
        score[i[absorbed]] = le
        alive[i[absorbed]] = False
        i = i[~absorbed]
        z = rng.uniform(-1, 1, len(i))
        phi = rng.uniform(0, 2 * np.pi, len(i))
        r = np.sqrt(1 - z * z)
        d[i] = np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
    return score.mean(), score.std(ddof=1) / np.sqrt(n)


def test03_emission_and_scattering_match_a_random_walk(llvm):
    """A glowing, scattering cube (albedo 0.7, tau 2 across) made of two
    levels of cells with one value, against `random_walk_radiance`: the
    difference within five standard errors of both estimates."""
    sigma, albedo, le = 2.0, 0.7, 1.5
    cells = two_level_cells()
    cells = AMRCells(cells.pos, cells.level, np.full(len(cells), 0.5))
    medium = {"type": "amr", "data": cells, "transfer_function": flat_tf((albedo,) * 3, 1.0),
              "density_scale": sigma, "emission": flat_tf((1.0, 1.0, 1.0), 1.0), "emission_scale": le}
    scene = mi.load_dict(ortho_scene(medium, res=16))
    mean, err = mean_and_error(mi.render(scene, spp=256, seed=7))
    walk, walk_err = random_walk_radiance(sigma, albedo, le)
    tol = 5 * np.sqrt(err ** 2 + walk_err ** 2)
    assert np.all(np.abs(mean - walk) < tol), (mean, walk, tol)
    # and more than the absorbing-only answer: scattered paths glow too
    assert mean.mean() > le * (1 - albedo) * (1 - np.exp(-sigma)) + tol.max()


def test04_emission_changes_without_recompiling_in_frozen_frames(llvm):
    """A frozen render follows emission_scale and emission_rgba changes
    made through ``params.update()`` (recorded once), scaling the image as
    the change says; the majorants do not move."""
    medium = {"type": "amr", "data": uniform_cells(), "transfer_function": BLACK, "density_scale": 1.0,
              "reconstruction": "nearest", "emission": flat_tf(GLOW, 1.0)}
    scene = mi.load_dict(ortho_scene(medium, res=8))
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("emission_scale"))
    rgba_key = key.replace("emission_scale", "emission_rgba")
    med = next(s.interior_medium() for s in scene.shapes() if s.interior_medium() is not None)
    majorant = med.global_majorant

    @dr.freeze
    def render(scene, seed):
        return mi.render(scene, spp=4, seed=seed)

    for seed in (1, 2, 3):                  # past the first replays (as tests/test_conformance.py)
        a = np.array(render(scene, dr.opaque(mi.UInt32, seed)))
    recordings = render.n_recordings
    params[key] = 3.0
    params.update()
    b = np.array(render(scene, dr.opaque(mi.UInt32, 3)))
    params[rgba_key] = mi.Float(np.tile([0.0, 1.0, 0.0, 0.5], 2))
    params.update()
    c = np.array(render(scene, dr.opaque(mi.UInt32, 3)))
    assert render.n_recordings == recordings
    np.testing.assert_allclose(c, np.array(mi.render(scene, spp=4, seed=3)), rtol=1e-4, atol=1e-5)
    assert med.global_majorant == majorant
    np.testing.assert_allclose(b, 3.0 * a, rtol=1e-5, atol=1e-6)          # same paths, three times the light
    green = a[..., 0] / GLOW[0] * 3.0 * 0.5                               # the same hits, green at half intensity
    np.testing.assert_allclose(c[..., 1], green, rtol=1e-4, atol=1e-6)
    assert np.all(c[..., 0] == 0) and np.all(c[..., 2] == 0)


def test05_bad_emission_parameters_are_named(llvm):
    base = {"type": "amr", "data": two_level_cells(), "transfer_function": BLACK}
    for extra, words in [({"emission_scale": 2.0}, "without 'emission'"),
                         ({"emission": "blackbody", "emission_field": "pressure"}, "'pressure' is not a field"),
                         ({"emission": "blackbody", "emission_scale": -1.0}, "emission_scale"),
                         ({"emission": "blackbody", "emission_min": 3.0, "emission_max": 1.0}, "emission_min"),
                         ({"emission": "no-such-map"}, "no-such-map")]:
        with pytest.raises(Exception, match=words):
            mi.load_dict(ortho_scene(dict(base, **extra)))
    # a medium loaded without emission refuses emission changes, naming why
    scene = mi.load_dict(ortho_scene(dict(base)))
    med = next(s.interior_medium() for s in scene.shapes() if s.interior_medium() is not None)
    with pytest.raises(Exception, match="without emission"):
        med.set_emission(emission_scale=2.0)


def test06_stock_volpath_warns_that_it_ignores_emission(llvm, capfd):
    """Stock volpath has no medium emission: the medium says so once,
    naming amrvolpath, and the image holds no emitted light."""
    from mi_amr.plugins import medium as medium_module
    medium_module._WARNED.discard("emission")
    medium = {"type": "amr", "data": uniform_cells(), "transfer_function": BLACK, "density_scale": 1.0,
              "reconstruction": "nearest", "emission": "blackbody"}
    for _ in range(2):
        scene = mi.load_dict(dict(ortho_scene(medium, res=4), integrator={"type": "volpath"}))
        img = np.array(mi.render(scene, spp=2))
        assert np.all(img == 0)
    out = capfd.readouterr()
    text = out.out + out.err
    assert text.count("stock volpath has no medium emission") == 1 and "amrvolpath" in text, text


# ---- Two fields on the same cells ----------------------------------------------
def test07_a_second_field_survives_npz_and_amrb_and_is_checked(tmp_path):
    """A further field rides along in .npz (``field_NAME``) and .amrb files
    (streamed or whole, in block layout); a field for cells the data do
    not have, a cell left out, or a NaN is refused naming the field."""
    from mi_amr.data.amrb import read_amrb, write_amrb
    from mi_amr.data.blocks import BlockVolume
    from mi_amr.data.io import load_volume, read_npz, write_npz
    cells = two_level_cells()
    write_npz(cells, tmp_path / "two.npz")
    again = read_npz(tmp_path / "two.npz")
    np.testing.assert_array_equal(again.fields["temperature"], cells.fields["temperature"])
    for vol in (load_volume(tmp_path / "two.npz"), BlockVolume.from_cells(cells)):
        assert vol.field_range("temperature") == (2.0, 6.0)
        t, v = vol.field("temperature"), vol.values
        np.testing.assert_array_equal(np.isnan(t), np.isnan(v))                  # the same cells
        np.testing.assert_array_equal(t[v == np.float32(0.25)], 2.0)             # fine cells: 2
        np.testing.assert_array_equal(t[v == np.float32(0.75)], 6.0)             # coarse cells: 6
        stored = read_amrb(write_amrb(vol, tmp_path / "two.amrb"))
        np.testing.assert_array_equal(stored.fields["temperature"], t)
        back = stored.to_cells()
        order = np.lexsort(back.pos.T)
        ref = np.lexsort(cells.pos.T)
        np.testing.assert_array_equal(back.fields["temperature"][order], cells.fields["temperature"][ref])
    vol = BlockVolume.from_cells(cells)
    plain = BlockVolume.from_cells(AMRCells(cells.pos, cells.level, cells.value))
    assert vol.nbytes - plain.nbytes == vol.values.nbytes             # memory grows by the field alone
    with pytest.raises(ValueError, match="no field 'pressure'"):
        vol.field("pressure")
    pos, level = cells.pos, cells.level
    bad = [((pos + 64, level, cells.fields["temperature"]), "a cell the data do not have"),
           ((pos[1:], level[1:], cells.fields["temperature"][1:]), "each cell needs exactly one"),
           ((pos, level, np.where(np.arange(len(pos)) == 3, np.nan, 1.0)), "NaN or Inf")]
    for chunk, words in bad:
        with pytest.raises(ValueError, match=words):
            vol.add_field("x", lambda chunk=chunk: iter([chunk]))
        assert "x" not in vol.fields
    with pytest.raises(ValueError, match="field 'temperature' has NaN"):
        AMRCells(pos, level, cells.value, fields={"temperature": np.full(len(pos), np.inf)})


def _enzo_example(directory):
    """The README's Enzo-format example (tools/make_enzo_example.py: Density
    and Temperature, 64^3 root cells and 24 level-1 grids of 16^3)."""
    import importlib.util
    from pathlib import Path
    script = Path(__file__).resolve().parents[1] / "tools" / "make_enzo_example.py"
    spec = importlib.util.spec_from_file_location("make_enzo_example", script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.main(str(directory))
    return Path(directory) / "DD0018" / "DD0018"


@pytest.mark.slow   # default-suite budget: the path is covered by faster tests
def test08_two_fields_of_the_enzo_example_in_one_command(tmp_path, capsys):
    """``mi-amr render OUTPUT --field density --emission blackbody
    --emission-field temperature`` on the Enzo-format example: extinction
    from the density, glow from the temperature, on black (no other light);
    the scene written beside the image names both, and its data file
    (.amrb) holds the second field."""
    pytest.importorskip("yt")
    from mi_amr.data.amrb import read_amrb
    from mi_amr.tools.cli import main
    from mi_amr.images import read_exr
    out = tmp_path / "glow.exr"
    output = _enzo_example(tmp_path / "enzo")
    code = main(["render", str(output), "--field", "density", "--emission", "blackbody",
                 "--emission-field", "temperature", "-o", str(out), "--res", "24", "--spp", "8", "-q"])
    assert code == 0
    img = read_exr(out)
    assert np.isfinite(img).all() and img.mean() > 0.01
    xml = out.with_suffix(".xml").read_text()
    assert 'name="emission_field" value="temperature"' in xml and "sunsky" not in xml
    vol = read_amrb(out.with_suffix(".amrb"))
    assert "temperature" in vol.fields
    # no emission: the same data lit by the sun and sky, as before
    assert main(["render", str(output), "--field", "density", "-o",
                 str(tmp_path / "lit.exr"), "--res", "8", "--spp", "1", "-q"]) == 0
    assert "sunsky" in (tmp_path / "lit.xml").read_text()
    with pytest.raises(SystemExit, match="--emission"):
        main(["render", "scenes/cloud.xml", "--emission", "blackbody", "-o", str(tmp_path / "x.exr")])


def _series(directory, n=3):
    """A synthetic run: ``n`` outputs of a hot blob that grows and moves,
    density and temperature on two levels (.npz, as codes' converters
    write them)."""
    from mi_amr.data.io import write_npz
    directory.mkdir(parents=True, exist_ok=True)
    cells = two_level_cells()
    centre = (cells.pos + 0.5 * (1 << cells.level)[:, None]) / 8.0
    for k in range(n):
        r = np.linalg.norm(centre - [0.3 + 0.2 * k, 0.5, 0.5], axis=1)
        density = 1e-28 * np.exp(-(r / (0.2 + 0.05 * k)) ** 2) + 1e-31
        temperature = 1e3 + 1e6 * np.exp(-(r / 0.15) ** 2) * (k + 1)
        write_npz(AMRCells(cells.pos, cells.level, density, fields={"temperature": temperature}),
                  directory / f"t_{k:03d}.npz")
    return directory


def test09_a_runs_outputs_as_a_movie_in_one_command(tmp_path, capsys):
    """``mi-amr render 'run/t_*.npz' --movie run.mp4 --frames``: one frame per
    output with one TF range and emission range over all of them (the same
    in every frame's scene), an H.264 movie of that many frames, numbered
    EXR frames; an unreadable output is named, the others still render, and
    the exit status says one was left out."""
    pytest.importorskip("imageio_ffmpeg")
    import imageio_ffmpeg
    from mi_amr.tools.cli import main
    run = _series(tmp_path / "run")
    (run / "t_003.npz").write_bytes(b"not an archive")
    movie = tmp_path / "run.mp4"
    code = main(["render", str(run / "t_*.npz"), "--emission", "blackbody", "--emission-field", "temperature",
                 "--movie", str(movie), "--frames", "--orbit", "30", "-o", str(tmp_path / "run.exr"),
                 "--res", "16", "--spp", "2", "-q"])
    err = capsys.readouterr().err
    assert code == 1 and "t_003.npz" in err and "left out" in err
    reader = imageio_ffmpeg.read_frames(str(movie))
    meta = next(reader)
    assert tuple(meta["size"]) == (16, 16)
    assert sum(1 for _ in reader) == 3
    assert [p.name for p in sorted(tmp_path.glob("run_0*.exr"))] == ["run_000.exr", "run_001.exr", "run_002.exr"]
    scenes = [(tmp_path / "run_outputs" / f"{k:03d}.xml").read_text() for k in range(3)]

    def values(text, name):
        return text.split(f'name="{name}" value="')[1].split('"')[0]
    # --emission blackbody: Planck's law at the temperature in kelvin (no emission TF, no emission range)
    for name in ("tf_min", "tf_max", "emission_model", "emission_scale", "density_scale"):
        assert len({values(s, name) for s in scenes}) == 1, name          # one plan: colours do not jump
    assert values(scenes[0], "emission_model") == "blackbody" and 'name="emission_min"' not in scenes[0]
    assert len({s.split("<lookat origin=")[1].split('"')[1] for s in scenes}) == 3      # the orbit
    # nothing readable: an error naming the pattern's outputs, no movie
    assert main(["render", str(tmp_path / "none_*.npz"), "--movie", str(tmp_path / "x.mp4"),
                 "-o", str(tmp_path / "x.exr")]) == 2
    assert "no output matches" in capsys.readouterr().err


def test09b_denoise_applies_to_a_runs_frames_and_movie(tmp_path):
    """``--denoise`` with a run's outputs is not ignored: each numbered frame
    gets its ``-denoised`` copy (finite, and what the denoiser makes of
    that very frame, within 1e-4); the movie is written (from those
    frames, `_render_series`)."""
    pytest.importorskip("imageio_ffmpeg")
    from mi_amr.tools.cli import main
    from mi_amr.images import read_exr as read_image
    from mi_amr.view.engine import denoiser
    if denoiser()[0] is None:
        pytest.skip(denoiser()[1])
    run = _series(tmp_path / "run", n=2)
    code = main(["render", str(run / "t_*.npz"), "--emission", "blackbody", "--emission-field", "temperature",
                 "--movie", str(tmp_path / "run.mp4"), "--frames", "--denoise", "-o", str(tmp_path / "run.exr"),
                 "--res", "16", "--spp", "2", "-q"])
    assert code == 0 and (tmp_path / "run.mp4").stat().st_size > 0
    for k in range(2):
        noisy = read_image(tmp_path / f"run_{k:03d}.exr")[..., :3]
        clean = read_image(tmp_path / f"run_{k:03d}-denoised.exr")[..., :3]
        assert clean.shape == noisy.shape and np.all(np.isfinite(clean))
        assert np.allclose(clean, denoiser()[0](noisy), atol=1e-4) and not np.allclose(clean, noisy, atol=1e-4)


def test09c_a_movie_without_output_puts_its_frames_beside_it(tmp_path, capsys):
    """``--movie OUT.mp4`` without ``-o``: the movie, the numbered frames
    (``--frames``: OUT_000.exr, ...) and the scenes (OUT_outputs/) beside
    it, each naming the ``--mode`` it was rendered in; without --movie, -o
    is still needed: a one-line error, exit 2."""
    pytest.importorskip("imageio_ffmpeg")
    import imageio_ffmpeg
    from mi_amr.tools.cli import main
    run = _series(tmp_path / "run", n=2)
    movie = tmp_path / "films" / "run.mp4"
    assert main(["render", str(run / "t_*.npz"), "--movie", str(movie), "--frames", "--mode", "single",
                 "--res", "8", "--spp", "1", "-q"]) == 0
    reader = imageio_ffmpeg.read_frames(str(movie))
    next(reader)
    assert sum(1 for _ in reader) == 2
    assert sorted(p.name for p in movie.parent.glob("run_0*.exr")) == ["run_000.exr", "run_001.exr"]
    for k in range(2):
        assert '<string name="mode" value="single"/>' in (movie.parent / "run_outputs" / f"{k:03d}.xml").read_text()
    capsys.readouterr()
    assert main(["render", str(run / "t_*.npz"), "--res", "8"]) == 2
    err = capsys.readouterr().err
    assert "-o/--output is needed" in err and "--movie" in err and len(err.strip().splitlines()) == 1


@pytest.mark.slow
def test10_a_movie_on_dask_workers_equals_the_local_one(tmp_path):
    """``--workers 2``: the frames of a run rendered frame-parallel on a
    local Dask cluster equal those rendered here (same seeds)."""
    pytest.importorskip("dask.distributed")
    from mi_amr.tools.cli import main
    from mi_amr.images import read_exr
    run = _series(tmp_path / "run", n=2)
    args = ["render", str(run / "t_*.npz"), "--emission", "blackbody", "--emission-field", "temperature",
            "--frames", "--res", "12", "--spp", "4", "-q"]
    assert main(args + ["-o", str(tmp_path / "here.exr")]) == 0
    assert main(args + ["-o", str(tmp_path / "dask.exr"), "--workers", "2"]) == 0
    for k in range(2):
        np.testing.assert_allclose(read_exr(tmp_path / f"dask_{k:03d}.exr"), read_exr(tmp_path / f"here_{k:03d}.exr"),
                                   rtol=1e-5, atol=1e-6)
