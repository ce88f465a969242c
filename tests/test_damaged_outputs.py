"""Damaged input never crashes (issue 63): seeded, bounded damage to outputs
the package writes in the Enzo, AMReX and ``.amrb`` forms (a file truncated
at a random offset, a run of random bytes overwritten, one header line
replaced by another), each run through ``mi-amr render DATA --field F --res
16 --spp 1``, must end in a picture or a one-line refusal: no traceback, no
signal, no hang.

The cases run in one child process (one import of Mitsuba and yt for all of
them, the command line called in-process per case): a signal kills only the
child and names the case it was at; a case that runs past `CASE_TIMEOUT`
makes the child dump its stack and exit (`faulthandler`), naming the case.
"""

import gc
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("yt")
pytest.importorskip("h5py")

#: Cases per format and kind of damage (3 formats x 3 kinds x this).
PER_KIND = 2
#: Seconds one case may take before it counts as a hang (a render of 16x16
#: pixels at 1 spp takes about a second; the first compiles its kernels).
CASE_TIMEOUT = 240
SEED = 63


# ---- the outputs, as the package writes them --------------------------------------------------
def _enzo(root: Path):
    from mi_amr.data.enzo_example import write_enzo
    x, y, z = np.meshgrid(*[np.arange(8)] * 3, indexing="ij")
    top = 1.0 + 4.0 * np.exp(-((x - 4) ** 2 + (y - 3) ** 2 + (z - 4) ** 2) / 10.0)
    child = 3.0 + np.linspace(0, 2, 64).reshape(4, 4, 4)
    return write_enzo(root / "enzo", "DD0001", top, [((4, 4, 4), child)]), "Density"


def _amrex(root: Path):
    from amr_formats import write_amrex_plotfile
    x, y, z = np.meshgrid(*[(np.arange(8) + 0.5) / 8] * 3, indexing="ij")
    coarse = 1.0 + 4.0 * np.exp(-((x - 0.5) ** 2 + (y - 0.4) ** 2 + (z - 0.5) ** 2) / 0.05)
    fine = 3.0 + np.linspace(0, 2, 512).reshape(8, 8, 8)
    path = root / "amrex" / "plt00010"
    write_amrex_plotfile(path, [[((0, 0, 0), coarse)], [((4, 4, 4), fine)]], [0, 0, 0], [1, 1, 1])
    return path, "density"


def _amrb(root: Path):
    from conftest import random_amr
    from mi_amr.native_file import save_data
    (root / "amrb").mkdir(parents=True)
    return save_data(random_amr(seed=5, n=16, levels=3), root / "amrb" / "d.amrb"), "value"


FORMATS = {"enzo": _enzo, "amrex": _amrex, "amrb": _amrb}


def _files(output: Path) -> list[Path]:
    """The files of an output (a file, or a folder's files), sorted."""
    if output.is_dir():
        return sorted(p for p in output.rglob("*") if p.is_file())
    return sorted(p for p in output.parent.iterdir() if p.is_file() and p.name.startswith(output.name))


def _text(path: Path) -> bool:
    try:
        path.read_bytes().decode("ascii")
        return True
    except UnicodeDecodeError:
        return False


def damage(output: Path, kind: str, rng) -> str:
    """Damage one file of ``output`` in place; returns what was done."""
    files = _files(output)
    if kind == "line":
        texts = [f for f in files if _text(f) and f.stat().st_size > 0]
        if texts:
            f = texts[rng.integers(len(texts))]
            lines = f.read_text().splitlines()
            k = int(rng.integers(len(lines)))
            lines[k] = "garbage"
            f.write_text("\n".join(lines) + "\n")
            return f"{f.name}: line {k + 1} replaced by 'garbage'"
        kind = "bytes"                            # a binary format: its header bytes overwritten instead
        f = files[rng.integers(len(files))]
        data = bytearray(f.read_bytes())
        at, n = int(rng.integers(0, min(len(data), 512))), int(rng.integers(1, 16))
        data[at:at + n] = rng.integers(0, 256, min(n, len(data) - at), dtype=np.uint8).tobytes()
        f.write_bytes(bytes(data))
        return f"{f.name}: {n} header bytes at {at} overwritten"
    f = files[rng.integers(len(files))]
    data = f.read_bytes()
    if kind == "truncate":
        at = int(rng.integers(0, len(data)))
        f.write_bytes(data[:at])
        return f"{f.name}: truncated to {at} of {len(data)} bytes"
    data = bytearray(data)
    at, n = int(rng.integers(0, len(data))), int(rng.integers(1, 64))
    data[at:at + n] = rng.integers(0, 256, min(n, len(data) - at), dtype=np.uint8).tobytes()
    f.write_bytes(bytes(data))
    return f"{f.name}: {n} bytes at {at} overwritten"


# ---- the child: every case through the command line, in-process ---------------------------------
def run_cases(cases_json: str):
    """In the child process: each case of ``cases_json`` through
    ``mi-amr render``; one JSON line per case on stdout (its outcome, what
    it printed on stderr), a ``start`` line before it."""
    import contextlib
    import faulthandler
    import gc
    import io
    import traceback

    from mi_amr.tools.cli import main
    cases = json.loads(Path(cases_json).read_text())
    for case in cases:
        print(json.dumps({"start": case["name"]}), flush=True)
        faulthandler.dump_traceback_later(CASE_TIMEOUT, exit=True)
        err, out, outcome = io.StringIO(), io.StringIO(), {"name": case["name"]}
        argv = ["render", case["data"], "--field", case["field"], "--res", "16", "--spp", "1",
                "-o", case["exr"], "-q"]
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
            try:
                outcome["rc"] = main(argv)
            except SystemExit as e:
                outcome["rc"] = e.code if isinstance(e.code, int) else 2
                if not isinstance(e.code, int):
                    print(e.code, file=sys.stderr)
            except BaseException:               # noqa: BLE001: what the user would see, kept to report
                outcome["rc"] = "raised"
                outcome["traceback"] = traceback.format_exc()
            gc.collect()                         # what yt half built goes now: its __del__ speaks here
        faulthandler.cancel_dump_traceback_later()
        outcome["stderr"] = err.getvalue()
        outcome["picture"] = Path(case["exr"]).is_file()
        print(json.dumps(outcome), flush=True)


#: yt's own chatter on stderr, not part of a refusal: its log lines and its
#: progress bars ("Parsing Hierarchy : 100%|...| 2/2 [00:00<...]").
YT_CHATTER = re.compile(r"^yt : \[|\|\s*\d+/\d+ \[")


def _verdict(outcome: dict) -> str | None:
    """Why a case's outcome is neither a picture nor a one-line refusal (None: it is one)."""
    err = outcome["stderr"]
    if outcome["rc"] == "raised":
        return "a traceback:\n" + outcome["traceback"]
    if "Traceback" in err or "Exception ignored" in err:
        return "a traceback on stderr:\n" + err
    lines = [ln for ln in re.split(r"[\r\n]", err) if ln.strip() and not YT_CHATTER.search(ln)]
    if outcome["rc"] == 0:
        return None if outcome["picture"] else "exit 0 without a picture"
    if len(lines) != 1 or not lines[0].startswith("mi-amr"):
        return f"exit {outcome['rc']} without a one-line refusal: {err!r}"
    return None


def check_outcomes(outcomes: list[dict]):
    """Every outcome a picture or a one-line refusal (AssertionError naming the cases that are not)."""
    bad = {o["name"]: _verdict(o) for o in outcomes if _verdict(o)}
    assert not bad, "\n".join(f"{k}: {v}" for k, v in bad.items())


def test01_damaged_outputs_end_in_a_picture_or_one_line(tmp_path):
    """Each format x kind of damage x `PER_KIND` seeded cases; the pristine
    outputs render; every damaged one ends in a picture or a one-line
    refusal (counted: most are refusals), with no signal and no hang. The
    check itself fails on a traceback, a second line and a silent exit."""
    rng = np.random.default_rng(SEED)
    cases, what = [], {}
    for fmt, write in FORMATS.items():
        pristine, field = write(tmp_path / "pristine" / fmt)
        rel = pristine.relative_to(tmp_path / "pristine" / fmt)
        top = rel.parts[0]
        for kind in ("none", "truncate", "bytes", "line"):
            for k in range(1 if kind == "none" else PER_KIND):
                name = f"{fmt}-{kind}-{k}"
                shutil.copytree(tmp_path / "pristine" / fmt / top, tmp_path / name / top)
                data = tmp_path / name / rel
                what[name] = "pristine" if kind == "none" else damage(data, kind, rng)
                cases.append({"name": name, "data": str(data), "field": field,
                              "exr": str(tmp_path / name / "out.exr")})
    (tmp_path / "cases.json").write_text(json.dumps(cases))
    here = Path(__file__).resolve().parent
    code = (f"import sys; sys.path.insert(0, {str(here)!r}); import test_damaged_outputs as t; "
            f"t.run_cases({str(tmp_path / 'cases.json')!r})")
    env = dict(os.environ, PYTHONFAULTHANDLER="1")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                          timeout=CASE_TIMEOUT * len(cases))
    lines = [json.loads(ln) for ln in proc.stdout.splitlines() if ln.startswith("{")]
    started = [ln["start"] for ln in lines if "start" in ln]
    outcomes = [ln for ln in lines if "rc" in ln]
    assert proc.returncode == 0 and len(outcomes) == len(cases), (
        f"the child ended with {proc.returncode} (a signal when negative) at case "
        f"{started[-1] if started else None} ({what.get(started[-1]) if started else ''}):\n{proc.stderr[-4000:]}")
    for o in outcomes:
        o["what"] = what[o["name"]]
    check_outcomes(outcomes)
    pristine = [o for o in outcomes if o["what"] == "pristine"]
    assert len(pristine) == 3 and all(o["rc"] == 0 and o["picture"] for o in pristine), pristine
    refused = [o for o in outcomes if o["rc"] != 0]
    assert len(refused) >= len(cases) // 3, [(o["name"], o["what"], o["rc"]) for o in outcomes]
    hierarchy = [o for o in refused if "hierarchy" in o["what"]]
    assert all(".hierarchy" in o["stderr"] or "DD0001" in o["stderr"] for o in hierarchy), hierarchy
    # the check's power: a traceback, a second line and a silent exit each fail it
    one = dict(refused[0])
    for wrong in (dict(one, rc="raised", traceback="Traceback (most recent call last):\n  ...\nTypeError"),
                  dict(one, stderr=one["stderr"] + "Exception ignored in: <function GridIndex.__del__>\n"),
                  dict(one, stderr=one["stderr"] + "a second line\n"),
                  dict(one, rc=0, picture=False)):
        with pytest.raises(AssertionError):
            check_outcomes([wrong])


def test02_a_replaced_hierarchy_line_is_one_line_naming_the_file(tmp_path, capsys):
    """An Enzo ``.hierarchy`` whose ``BaryonFileName`` line is ``garbage``:
    yt's index parser fails with a TypeError; ``mi-amr render`` says so in
    one line naming the hierarchy file and what yt said (exit 2); with
    ``--traceback`` yt's own error is the cause of the one raised."""
    from mi_amr.data.yt_import import DamagedFile
    from mi_amr.tools.cli import main
    output, field = _enzo(tmp_path)
    hierarchy = output.with_suffix(".hierarchy")
    lines = ["garbage" if ln.startswith("BaryonFileName") else ln for ln in hierarchy.read_text().splitlines()]
    hierarchy.write_text("\n".join(lines) + "\n")
    argv = ["render", str(output), "--field", field, "--res", "16", "--spp", "1", "-o", str(tmp_path / "o.exr"), "-q"]
    assert main(argv) == 2
    gc.collect()                                 # what yt half built is gone, quietly
    said = capsys.readouterr().err
    err = [ln for ln in said.splitlines() if ln.startswith("mi-amr")]
    assert len(err) == 1 and str(hierarchy) in err[0] and "TypeError" in err[0], err
    assert "Traceback" not in said and "Exception ignored" not in said, said
    with pytest.raises(DamagedFile) as raised:
        main(argv + ["--traceback"])
    assert isinstance(raised.value.__cause__, TypeError)
