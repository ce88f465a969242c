"""Bad input to every entry point is one line: a missing or miscased field
(with the closest names), a truncated file of a simulation output (named),
a 2-D output, a bad argument (refused before any data are read); the
command line prints ``mi-amr CMD: error: ...`` and exits with status 2, and
``--traceback``/``MI_AMR_TRACEBACK=1`` show the traceback. ``mi-amr info
DATA`` without ``--field`` describes the data set from its index. Small
outputs in the codes' own formats (tests/amr_formats.py), damaged here."""

import json
import os
import shutil

import numpy as np
import pytest

from amr_formats import write_amrex_plotfile, write_athena_pp, write_enzo, write_ramses

yt = pytest.importorskip("yt")
pytest.importorskip("h5py")

from mi_amr.autoscene import plan_scene                                   # noqa: E402
from mi_amr.data.yt_import import DamagedFile, FieldNotFound, resolve_field   # noqa: E402
from mi_amr.tools.cli import main                                        # noqa: E402


@pytest.fixture(scope="module", autouse=True)
def quiet_yt():
    """yt's log lines and progress bars off (they are not our errors)."""
    level = yt.config.ytcfg.get("yt", "log_level")
    yt.set_log_level(50)
    yield
    yt.set_log_level(level)


@pytest.fixture(scope="module")
def outputs(tmp_path_factory):
    """Small outputs: ``enzo`` (8^3 root, one 4^3 level-1 grid, fields
    Density and Temperature), ``amrex`` (one 8^3 box), ``ramses`` (4^3 root
    cells, one refined: 63 + 8 leaves)."""
    root = tmp_path_factory.mktemp("outputs")
    rng = np.random.default_rng(0)
    enzo = write_enzo(root / "enzo", "DD0001", 1 + rng.random((8, 8, 8)), [((4, 4, 4), 2 + rng.random((4, 4, 4)))],
                      extra={"Temperature": lambda d: 100.0 * d})
    amrex = write_amrex_plotfile(root / "plt00001", [[((0, 0, 0), 1 + rng.random((8, 8, 8)))]], [0, 0, 0], [1, 1, 1])

    def value(level, ijk):
        rho = 1.0 + level + ijk[:, 0] / 8.0
        return np.stack([rho, 0 * rho, 0 * rho, 0 * rho, rho / 10], axis=1)
    ramses = write_ramses(root / "ramses", 2, [np.array([[0, 0, 0]])], value)
    return {"enzo": enzo, "amrex": amrex, "ramses": ramses}


def copy_output(outputs, code, tmp_path):
    """A copy of an output (its folder) to damage; returns the copy's path."""
    src = outputs[code]
    folder = src if src.is_dir() else src.parent
    shutil.copytree(folder, tmp_path / folder.name)
    return tmp_path / folder.name / src.relative_to(folder) if src != folder else tmp_path / folder.name


def truncate(path, keep):
    """Cut ``path`` to ``keep`` bytes (a fraction below 1: of its size)."""
    size = os.path.getsize(path)
    os.truncate(path, int(size * keep) if keep < 1 else int(keep))


def one_error(capsys, argv, command=None) -> str:
    """``mi-amr ARGV`` in this process: exit status 2 and exactly one line
    on stderr (besides yt's progress bars), ``mi-amr CMD: error: ...``, no
    traceback; returns it. An argparse refusal (SystemExit 2) counts the same."""
    try:
        code = main([str(a) for a in argv])
    except SystemExit as e:
        code = e.code
    err = capsys.readouterr().err
    lines = [ln for ln in err.replace("\r", "\n").splitlines() if ln.strip() and "%|" not in ln]   # not yt's bars
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, (code, err)
    assert lines[0].startswith(f"mi-amr {command or argv[0]}: error: "), lines[0]
    return lines[0]


# ---- fields ------------------------------------------------------------------
def test01_a_misspelt_field_names_the_closest(outputs, capsys, tmp_path):
    """``--field Temprature`` on an Enzo output: one line from render and
    info, the suggestion (difflib) and the fields on disk; the Python API
    raises one FieldNotFound with the same one-line message."""
    for argv in (["render", outputs["enzo"], "--field", "Temprature", "-o", tmp_path / "x.exr", "-q"],
                 ["info", outputs["enzo"], "--field", "Temprature"]):
        line = one_error(capsys, argv)
        assert "no field 'Temprature'" in line and "did you mean Temperature?" in line, line
        assert "enzo,Density" in line and str(outputs["enzo"]) in line, line
    with pytest.raises(FieldNotFound) as e:
        plan_scene(str(outputs["enzo"]), "rho")
    assert "\n" not in str(e.value) and "no field 'rho'" in str(e.value) and "did you mean" not in str(e.value)


def test02_fields_as_users_type_them(outputs):
    """`resolve_field`: yt's names and rule for bare names, TYPE,NAME,
    tuples, any case when one field matches (gas first); ambiguous and
    malformed names are refused."""
    ds = yt.load(str(outputs["enzo"]))
    assert resolve_field(ds, "density") == ("gas", "density")
    assert resolve_field(ds, "Density") == ("enzo", "Density")
    assert resolve_field(ds, ("gas", "density")) == ("gas", "density")
    assert resolve_field(ds, "enzo,Density") == ("enzo", "Density")
    assert resolve_field(ds, "ENZO, density") == ("enzo", "Density")
    assert resolve_field(ds, "TEMPERATURE") == ("gas", "temperature")
    ramses = yt.load(str(outputs["ramses"]))
    assert resolve_field(ramses, "x-VELOCITY") == ("ramses", "x-velocity")
    for bad, words in (("a,b,c", "NAME or TYPE,NAME"), ("enzo,Densty", "did you mean enzo,Density?"),
                       ("", "NAME or TYPE,NAME")):
        with pytest.raises(FieldNotFound, match=words):
            resolve_field(ds, bad)


# ---- damaged files -----------------------------------------------------------
DAMAGES = {          # code, file to cut (relative to the output's folder), bytes kept, the file's name in the error
    "enzo-grids": ("enzo", "DD0001.cpu0000", 0.5, "DD0001.cpu0000"),
    "amrex-values": ("amrex", "Level_0/Cell_D_00000", 0.5, "Cell_D_00000"),
    "amrex-fab-header": ("amrex", "Level_0/Cell_D_00000", 10, "Cell_D_00000"),
    "ramses-hydro": ("ramses", "hydro_00001.out00001", 0.6, "hydro_00001.out00001"),
    "ramses-amr": ("ramses", "amr_00001.out00001", 0.6, "amr_00001.out00001"),
}


@pytest.mark.parametrize("case", sorted(DAMAGES))
def test03_a_truncated_file_is_named(outputs, capsys, tmp_path, case):
    """A truncated grid, FAB or Fortran record file: ``mi-amr info`` and the
    Python API name the file and say it is truncated or damaged, in one
    line (yt's own message follows in brackets)."""
    code, name, keep, shown = DAMAGES[case]
    data = copy_output(outputs, code, tmp_path)
    folder = data if data.is_dir() else data.parent
    truncate(folder / name, keep)
    line = one_error(capsys, ["info", data, "--field", "density"])
    assert f"{shown}: truncated or damaged file of this " in line, line
    with pytest.raises(DamagedFile) as e:
        plan_scene(str(data), "density")
    assert os.path.basename(e.value.path) == shown and "\n" not in str(e.value)


@pytest.mark.parametrize("suffix", [".cells", ".scalars"])
def test04_truncated_cells_files_are_named(capsys, tmp_path, suffix):
    """A ``.cells`` file or its ``.scalars`` cut short: one line naming it."""
    assert main(["dataset", "cloud", str(tmp_path / "c.cells"), "--cells", "300"]) == 0
    capsys.readouterr()
    truncate(tmp_path / f"c{suffix}", 0.5 if suffix == ".cells" else 13)
    line = one_error(capsys, ["info", tmp_path / "c.cells"])
    assert f"c{suffix}" in line and "truncated" in line, line


# ---- 2-D outputs ---------------------------------------------------------------
def write_amrex_2d(path):
    """A 2-D AMReX plotfile: one 8 x 8 box over the unit square."""
    (path / "Level_0").mkdir(parents=True)
    (path / "Header").write_text("\n".join(["HyperCLaw-V1.1", "1", "density", "2", "0.0", "0", "0 0", "1 1", "",
                                            "((0,0) (7,7) (0,0))", "0", "0.125 0.125", "0", "0", "0 1 0.0", "0",
                                            "0 1", "0 1", "Level_0/Cell"]) + "\n")
    with open(path / "Level_0" / "Cell_D_00000", "wb") as f:
        f.write(b"FAB ((8, (64 11 52 0 1 12 0 1023)),(8, (8 7 6 5 4 3 2 1)))((0,0) (7,7) (0,0)) 1\n")
        f.write(np.ones(64, "<f8").tobytes())
    (path / "Level_0" / "Cell_H").write_text("1\n0\n1\n0\n(1 0\n((0,0) (7,7) (0,0))\n)\n1\nFabOnDisk: Cell_D_00000 0\n")
    return path


def test05_2d_outputs_are_refused_as_2d(outputs, capsys, tmp_path):
    """A 2-D AMReX plotfile, a 2-D Athena++ file and a RAMSES output whose
    info file says ndim 2 (yt takes every RAMSES output for 3-D and fails
    later on the records): one line, "a 2-D <code> output", from info,
    render and the Python API."""
    ramses = copy_output(outputs, "ramses", tmp_path)
    ramses.write_text(ramses.read_text().replace("ndim        =          3", "ndim        =          2"))
    cases = {"AMReX/BoxLib": write_amrex_2d(tmp_path / "plt2d"),
             "Athena++": write_athena_pp(tmp_path / "flat.athdf", [[((0, 0, 0), np.ones((8, 8, 1)))]], [8, 8, 1]),
             "RAMSES": ramses}
    for code, data in cases.items():
        assert f"a 2-D {code} output" in one_error(capsys, ["info", data])
        line = one_error(capsys, ["render", data, "--field", "density", "-o", tmp_path / "x.exr", "-q"])
        assert f"{data}: a 2-D {code} output" in line, line
        with pytest.raises(ValueError, match="a 2-D"):
            plan_scene(str(data), "density")


# ---- arguments -------------------------------------------------------------------
ARGUMENT_ERRORS = [
    (["render", "{data}", "--field", "density", "-o", "{out}", "--res", "-5"], "--res: -5: at least 1"),
    (["render", "{data}", "--field", "density", "-o", "{out}", "--spp", "0"], "--spp: 0: at least 1"),
    (["render", "{data}", "--field", "density", "-o", "{out}", "--range", "3", "1"], "--range: 3 1: LO must be below"),
    (["render", "{data}", "--field", "density", "-o", "{out}", "--range", "0", "inf"], "--range: inf: not finite"),
    (["render", "{data}", "--field", "density", "-o", "{out}", "--mode", "ambient"], "invalid choice: 'ambient'"),
    (["render", "{data}", "--emission", "blackbody", "-o", "{out}", "--emission-scale", "0"], "must be > 0"),
    (["view", "{data}", "--field", "density", "--max-spp", "0"], "--max-spp: 0: at least 1"),
    (["view", "{data}", "--field", "density", "--preview-scale", "-1"], "--preview-scale: -1: must be > 0"),
    (["convert", "{data}", "{out}", "--field", "density", "--max-level", "-1"], "--max-level: -1: at least 0"),
]


@pytest.mark.parametrize("argv,words", ARGUMENT_ERRORS, ids=[a[-2] + a[-1] for a, _ in ARGUMENT_ERRORS])
def test06_bad_arguments_are_refused_before_the_data(outputs, capsys, tmp_path, monkeypatch, argv, words):
    """A bad argument is refused in one line, exit status 2, before any
    data are opened: on a path that does not exist the error is the
    argument's, and on an output the loader is never called."""
    def never(*a, **k):
        raise AssertionError("the data were read before the arguments were checked")
    monkeypatch.setattr("mi_amr.data.yt_import.load_dataset", never)
    monkeypatch.setattr("mi_amr.data.opening.load_dataset", never)
    for data in (tmp_path / "missing" / "DD0001", outputs["enzo"]):
        line = one_error(capsys, [a.format(data=data, out=tmp_path / "o.exr") for a in argv])
        assert words in line and "missing" not in line, line


# ---- info without a field ------------------------------------------------------
def test07_info_without_field_describes_the_data_set(outputs, capsys, monkeypatch):
    """``mi-amr info DATA`` on yt data: code, domain, grids/octs and cells
    per level with their sizes (yt's numbering, 0 the root), every field
    with its units; from the index alone (no cells are opened). RAMSES:
    the leaves per level fill the domain's volume exactly."""
    def never(*a, **k):
        raise AssertionError("info without --field read the values")
    monkeypatch.setattr("mi_amr.tools.info.open_data", never)
    assert main(["info", str(outputs["enzo"]), "--json"]) == 0
    info = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert info["code"] == "Enzo" and info["index"] == "grids" and info["domain"]["root_cells"] == [8, 8, 8]
    assert [(r["level"], r["grids"], r["cells"], r["cell_size"]) for r in info["levels"]] == \
        [(0, 1, 512, [0.125] * 3), (1, 1, 64, [0.0625] * 3)]
    assert info["fields_on_disk"] == {"enzo,Density": "code_mass / code_length**3", "enzo,Temperature": "K"}
    assert info["fields_derived"]["gas,density"] == "g/cm**3"
    assert main(["info", str(outputs["ramses"]), "--json"]) == 0
    info = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    rows = info["levels"]
    assert [(r["octs"], r["leaf_cells"]) for r in rows] == [(8, 63), (1, 8)]
    assert sum(r["leaf_cells"] * np.prod(r["cell_size"]) for r in rows) == pytest.approx(1.0, rel=1e-12)
    assert info["fields_on_disk"]["ramses,Density"] == "code_density"
    assert main(["info", str(outputs["enzo"])]) == 0
    text = capsys.readouterr().out
    for words in ("code         : Enzo", "level  0: 1 grids, 512 cells; cells of 0.125 x 0.125 x 0.125 code_length",
                  "level  1: 1 grids, 64 cells", "enzo,Temperature [K]", "density [g/cm**3]"):
        assert words in text, words


# ---- tracebacks ------------------------------------------------------------------
def test08_tracebacks_on_request_and_for_bugs(outputs, capsys, monkeypatch, tmp_path):
    """``--traceback`` and ``MI_AMR_TRACEBACK=1`` let the exception through
    (Python prints its traceback); a bug (an error outside the expected
    classes) is never turned into one line."""
    missing = tmp_path / "nothing.cells"
    assert "nothing.cells" in one_error(capsys, ["info", missing])
    with pytest.raises(FileNotFoundError):
        main(["info", str(missing), "--traceback"])
    monkeypatch.setenv("MI_AMR_TRACEBACK", "1")
    with pytest.raises(FileNotFoundError):
        main(["info", str(missing)])
    monkeypatch.delenv("MI_AMR_TRACEBACK")

    def bug(*a, **k):
        raise TypeError("a bug")
    monkeypatch.setattr("mi_amr.tools.cli.describe", bug)
    with pytest.raises(TypeError):
        main(["info", str(outputs["enzo"])])
