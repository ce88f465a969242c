"""tools/gpu-check (``make test-gpu``) where there is no GPU, and the doc it
writes from what it measured (fake inputs); tools/test-gpu's choice of
Python and tools/gpu-wheels' slim Mitsuba wheel (fake tiny wheels). Cheap:
no suite, no benchmark, no download, no Dr.Jit kernel."""

import base64
import hashlib
import importlib.util
import os
import shutil
import subprocess
import sys
import zipfile
from importlib.machinery import SourceFileLoader
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "tools" / "gpu-check"


def _load(path, name):
    loader = SourceFileLoader(name, str(path))
    module = importlib.util.module_from_spec(importlib.util.spec_from_loader(name, loader))
    loader.exec_module(module)
    return module


def _gpu_check():
    return _load(SCRIPT, "gpu_check")


def _run(tmp_path, nvidia_smi):
    doc = tmp_path / "cuda.md"
    out = subprocess.run([sys.executable, str(SCRIPT), "--nvidia-smi", str(nvidia_smi), "--doc", str(doc),
                          "--out", str(tmp_path / "out")], capture_output=True, text=True, timeout=120,
                         env={**os.environ, "OUT": str(tmp_path / "device-out")})
    return out, doc


def test01_without_nvidia_smi_it_says_so_in_one_line_and_writes_nothing(tmp_path):
    out, doc = _run(tmp_path, tmp_path / "no-such-nvidia-smi")
    lines = (out.stdout + out.stderr).strip().splitlines()
    assert out.returncode == 1 and len(lines) == 1 and "no CUDA GPU" in lines[0], lines
    assert not doc.exists() and not (tmp_path / "out").exists() and not (tmp_path / "device-out").exists()


def test02_without_dr_jit_cuda_it_says_so_in_one_line_and_writes_nothing(tmp_path):
    import drjit as dr
    if dr.has_backend(dr.JitBackend.CUDA):
        pytest.skip("a CUDA GPU is here: the check would run the suite")
    smi = tmp_path / "nvidia-smi"
    smi.write_text('#!/bin/sh\necho "NVIDIA H200, 550.54.15, 143771 MiB"\n')
    smi.chmod(0o755)
    out, doc = _run(tmp_path, smi)
    lines = (out.stdout + out.stderr).strip().splitlines()
    assert out.returncode == 1 and len(lines) == 1 and "CUDA backend" in lines[0], lines
    assert not doc.exists()


def test03_the_doc_reports_gpu_counts_and_benchmark_and_keeps_earlier_runs(tmp_path):
    gc = _gpu_check()
    junit = tmp_path / "junit.xml"
    junit.write_text('<?xml version="1.0"?><testsuites><testsuite name="pytest" tests="5" failures="1" '
                     'errors="0" skipped="1" time="301.5">'
                     '<testcase classname="tests.test_medium" name="test01_a"/>'
                     '<testcase classname="tests.test_medium" name="test02_b"><failure message="x"/></testcase>'
                     '</testsuite></testsuites>')
    counts = gc.suite_counts(junit)
    assert counts["passed"] == 3 and counts["failed"] == ["tests.test_medium::test02_b"]
    assert gc.suite_counts(tmp_path / "missing.xml") is None
    records = [{"dataset": "cloud", "tf": "spiky", "config": "amrvolpath/default", "seconds_per_spp": 0.0053,
                "efficiency_vs_reference": 3.29, "lookups_per_collision": 9.2, "resolved": "grid/hash, grid 8x8x8"},
               {"dataset": "cloud", "tf": "spiky", "config": "reference", "skipped": "too large"}]
    run = {"date": "2027-01-05 14:03 UTC", "commit": "abc1234",
           "gpu": {"name": "NVIDIA H200", "driver": "550.54.15", "memory": "143771 MiB", "count": 1},
           "versions": {"mitsuba": "3.9.1", "drjit": "1.5.0"},
           "suite": {"rc": 1, "seconds": 302.0, "timed_out": False, "limit_s": 330, "command": "pytest",
                     "counts": counts},
           "bench": {"rc": 0, "seconds": 150.0, "timed_out": True, "limit_s": 200, "command": "bench",
                     "records": records}}
    doc = gc.render_doc(gc.run_section(run), gc.empty_doc())
    assert gc.NOT_RUN not in doc and doc.startswith(gc.HEADER)
    for text in ("## 2027-01-05 14:03 UTC: NVIDIA H200, driver 550.54.15", "Mitsuba 3.9.1, Dr.Jit 1.5.0",
                 "3 passed, 1 failed, 0 errors, 1 skipped of 5, in 302 s", "`tests.test_medium::test02_b`",
                 "stopped at the limit", "| cloud / spiky | amrvolpath/default | 5.30 | 3.29x | 9.2 | grid/hash",
                 "| cloud / spiky | reference | skipped: too large |"):
        assert text in doc, text
    run2 = {**run, "date": "2027-02-01 09:00 UTC"}
    doc2 = gc.render_doc(gc.run_section(run2), doc)
    assert doc2.index("2027-02-01") < doc2.index("2027-01-05") and doc2.count("## 2027-01-05") == 1


def test04_the_committed_doc_and_the_budget_match_the_script():
    """docs/performance/cuda.md opens with the script's header (how to run
    it), and the default limits keep the call under 10 minutes."""
    gc = _gpu_check()
    assert (ROOT / "docs" / "performance" / "cuda.md").read_text().startswith(gc.HEADER)
    args = gc.parse_args([])
    assert args.test_timeout < args.budget and args.budget + gc.GRACE_S + 30 < 600


def test05_outputs_are_also_written_to_the_device_out_folder(tmp_path):
    """A part's log goes to ``--out`` and, line by line, to ``$OUT`` (what
    the device tool copies back); `mirror` copies a finished file there."""
    gc = _gpu_check()
    out_dir = tmp_path / "OUT"
    r = gc.run_limited([sys.executable, "-c", "print('one'); print('two')"], dict(os.environ), 60,
                       tmp_path / "pytest.log", out_dir)
    assert r["rc"] == 0 and not r["timed_out"]
    assert (tmp_path / "pytest.log").read_text() == (out_dir / "pytest.log").read_text() == "one\ntwo\n"
    (tmp_path / "junit.xml").write_text("<testsuites/>")
    gc.mirror(tmp_path / "junit.xml", out_dir)
    gc.mirror(tmp_path / "missing.json", out_dir)
    gc.mirror(tmp_path / "junit.xml", None)
    assert sorted(p.name for p in out_dir.iterdir()) == ["junit.xml", "pytest.log"]


def _hash(data: bytes) -> str:
    return "sha256=" + base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()


def _fake_wheel(path, members):
    """A wheel with ``members`` (name -> bytes) and a RECORD that lists them."""
    dist = "mitsuba-3.9.1.dist-info"
    members = {**members, f"{dist}/METADATA": b"Metadata-Version: 2.1\nName: mitsuba\nVersion: 3.9.1\n",
               f"{dist}/WHEEL": b"Wheel-Version: 1.0\nRoot-Is-Purelib: false\nTag: cp312-cp312-manylinux_2_28_x86_64\n"}
    record = "".join(f"{n},{_hash(d)},{len(d)}\n" for n, d in members.items()) + f"{dist}/RECORD,,\n"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        for n, d in members.items():
            z.writestr(n, d)
        z.writestr(f"{dist}/RECORD", record)
    return members


def test06_the_slim_mitsuba_wheel_keeps_the_rgb_variants_and_a_consistent_record(tmp_path):
    """tools/gpu-wheels keeps scalar_rgb, llvm_ad_rgb and cuda_ad_rgb (the
    variants the project uses), plugins, data, libraries and the Python
    package; drops the other variant modules, the C++ headers and the
    spectral-upsampling table; RECORD loses exactly the dropped lines and
    every hash left still holds; METADATA and WHEEL are untouched."""
    gw = _load(ROOT / "tools" / "gpu-wheels", "gpu_wheels")
    so = ".cpython-312-x86_64-linux-gnu.so"
    keep = ["mitsuba/__init__.py", "mitsuba/python/util.py", "/".join(("mitsuba", "plugins", "path.so")), "mitsuba/libmitsuba.so",
            "mitsuba/data/ior/Au.eta.spd", "mitsuba/mitsuba_alias" + so, "mitsuba/mitsuba_ext" + so,
            "mitsuba/scalar_rgb" + so, "mitsuba/llvm_ad_rgb" + so, "mitsuba/cuda_ad_rgb" + so]
    drop = ["mitsuba/include/mitsuba/mitsuba.h", "mitsuba/data/srgb.coeff", "mitsuba/scalar_spectral" + so,
            "mitsuba/scalar_spectral_polarized" + so, "mitsuba/llvm_ad_mono" + so,
            "mitsuba/llvm_ad_mono_polarized" + so, "mitsuba/cuda_ad_spectral" + so,
            "mitsuba/cuda_ad_spectral_polarized" + so]
    src = tmp_path / "full" / "mitsuba-3.9.1-cp312-cp312-manylinux_2_28_x86_64.whl"
    src.parent.mkdir()
    members = _fake_wheel(src, {n: n.encode() * 50 for n in keep + drop})
    dst = tmp_path / "slim" / src.name
    gone = gw.slim_wheel(src, dst)
    assert sorted(gone) == sorted(drop)
    assert gw.check_record(src) == [] and gw.check_record(dst) == []
    with zipfile.ZipFile(dst) as z:
        names = set(z.namelist())
        record = z.read("mitsuba-3.9.1.dist-info/RECORD").decode()
        for n in ("METADATA", "WHEEL"):
            assert z.read(f"mitsuba-3.9.1.dist-info/{n}") == members[f"mitsuba-3.9.1.dist-info/{n}"]
    assert set(keep) <= names and not names & set(drop)
    assert all(n in record for n in keep) and not any(n in record for n in drop)
    with zipfile.ZipFile(dst, "a") as z:                # a member RECORD does not list is found
        z.writestr("mitsuba/extra.py", b"x")
    assert gw.check_record(dst) == ["not in RECORD: mitsuba/extra.py"]


def _test_gpu_copy(tmp_path):
    """tools/test-gpu and tools/find-llvm19 in a folder of their own (no .venv, no .whl)."""
    (tmp_path / "tools").mkdir()
    for name in ("test-gpu", "find-llvm19"):
        shutil.copy2(ROOT / "tools" / name, tmp_path / "tools" / name)
    return tmp_path / "tools" / "test-gpu"


def test07_test_gpu_without_venv_or_wheels_says_so_in_one_line(tmp_path):
    script = _test_gpu_copy(tmp_path)
    out = subprocess.run([str(script)], capture_output=True, text=True, timeout=60)
    lines = (out.stdout + out.stderr).strip().splitlines()
    assert out.returncode == 1 and len(lines) == 1 and "tools/gpu-wheels" in lines[0], lines


def test08_test_gpu_installs_the_wheels_offline_and_runs_the_check_with_them(tmp_path):
    """With .whl/ and no .venv: pip installs the wheels without network into
    $MI_AMR_SITE, and tools/gpu-check runs on python3 with that folder and
    the checkout on PYTHONPATH, unbuffered, with the arguments passed on
    (python3 is a fake that logs its calls)."""
    script = _test_gpu_copy(tmp_path)
    (tmp_path / ".whl").mkdir()
    (tmp_path / ".whl" / "a-1.0-py3-none-any.whl").write_bytes(b"")
    bin_dir, log = tmp_path / "bin", tmp_path / "calls.log"
    bin_dir.mkdir()
    (bin_dir / "python3").write_text(f'#!/bin/sh\necho "$PYTHONPATH|$PYTHONUNBUFFERED|$*" >> {log}\n')
    (bin_dir / "python3").chmod(0o755)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONUNBUFFERED")}
    env.update(PATH=f"{bin_dir}:/usr/bin:/bin", MI_AMR_SITE=str(tmp_path / "site"))
    out = subprocess.run([str(script), "--budget", "100"], capture_output=True, text=True, timeout=60,
                         env=env, cwd=tmp_path / "bin")
    assert out.returncode == 0, out.stdout + out.stderr
    pip, check = log.read_text().splitlines()
    assert pip.startswith("||-m pip install -q --no-index --no-deps ") and "--upgrade" in pip
    assert pip.endswith(f"--target {tmp_path / 'site'} .whl/a-1.0-py3-none-any.whl")
    assert check == f"{tmp_path / 'site'}:{tmp_path}|1|tools/gpu-check --budget 100"
