"""tools/gpu-check (``make test-gpu``) where there is no GPU, and the doc it
writes from what it measured (fake inputs). Cheap: no suite, no benchmark."""

import importlib.util
import subprocess
import sys
from importlib.machinery import SourceFileLoader
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "tools" / "gpu-check"


def _gpu_check():
    loader = SourceFileLoader("gpu_check", str(SCRIPT))
    module = importlib.util.module_from_spec(importlib.util.spec_from_loader("gpu_check", loader))
    loader.exec_module(module)
    return module


def _run(tmp_path, nvidia_smi):
    doc = tmp_path / "cuda.md"
    out = subprocess.run([sys.executable, str(SCRIPT), "--nvidia-smi", str(nvidia_smi), "--doc", str(doc),
                          "--out", str(tmp_path / "out")], capture_output=True, text=True, timeout=120)
    return out, doc


def test01_without_nvidia_smi_it_says_so_in_one_line_and_writes_nothing(tmp_path):
    out, doc = _run(tmp_path, tmp_path / "no-such-nvidia-smi")
    lines = (out.stdout + out.stderr).strip().splitlines()
    assert out.returncode == 1 and len(lines) == 1 and "no CUDA GPU" in lines[0], lines
    assert not doc.exists() and not (tmp_path / "out").exists()


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
