# Two commands do all the set-up on a fresh Debian machine:
#   make demo   renders scenes/demo.xml to out/demo.exr (+ .png)
#   make test   runs the test suite (fast default; markers: docs/manual/setup.md)
#   make docs   builds the manual (docs/, mkdocs.yml) into site/
SHELL := /bin/sh
PY    := .venv/bin/python
RUN   := DRJIT_LIBLLVM_PATH="$$(tools/find-llvm19)" $(PY)
SPP   ?= 64
PYTEST_ARGS ?=
# test processes: one per core (pytest-xdist), whole files per process so that
# module fixtures are made once; JOBS=0 runs the suite in this process
JOBS  ?= auto
XDIST  = $(if $(filter 0,$(JOBS)),,-n $(JOBS) --dist loadfile)

.PHONY: setup peers demo docs gallery test test-all test-gpu bench bench-quick bench-scale clean

setup:
	@tools/setup.sh

# optional benchmark peers (bench --peers eradiate): .venv-eradiate with
# Eradiate's Mitsuba fork (it pins its own Dr.Jit)
peers: setup
	@tools/setup-peers.sh

demo: setup
	$(RUN) -m mi_amr.tools.cli render scenes/demo.xml -o out/demo.exr --spp $(SPP)

# the manual (MkDocs, Material, mkdocstrings) into site/; --strict: a broken link
# or reference fails (tests/test_docs.py test07 builds it the same way)
docs: setup
	NO_MKDOCS_2_WARNING=1 .venv/bin/python -m mkdocs build --strict -d site

# the front-page images (docs/images, committed): minutes on 2 cores
gallery: setup
	$(RUN) -m mi_amr.tools.gallery

test: setup
	$(RUN) -m pytest -q $(XDIST) $(PYTEST_ARGS)

test-all: setup
	$(RUN) -m pytest -q -m "" $(XDIST) $(PYTEST_ARGS)

# on a machine with a CUDA GPU: the fast suite on cuda_ad_rgb and the 20k
# benchmark on CUDA in under 10 minutes, written to docs/performance/cuda.md;
# without a GPU it says so and fails. Uses .venv, else the wheels in .whl/
# (tools/gpu-wheels: for a GPU machine without network); see tools/test-gpu
test-gpu:
	@tools/test-gpu $(GPU_CHECK_ARGS)

clean:
	rm -rf out .pytest_cache

bench-quick: setup
	$(RUN) -m mi_amr.bench --quick --out out/bench-quick

bench: setup
	$(RUN) -m mi_amr.bench --out out/bench

# load, build, memory and frame time from 10^5 to 10^8 cells (writes ~2 GB of data to out/data)
bench-scale: setup
	$(RUN) -m mi_amr.bench --scale 1e7 1e8 --out out/bench-scale
