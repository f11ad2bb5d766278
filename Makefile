# The README's two commands: `make demo` (install + whole DAG on the embedded synthetic benchmark)
# and `make test` (install + `ruff check` + test suite).  Everything installs into .venv.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
# Exact versions of every package (docs/environment.md): a pip constraints file compiled by uv from
# pyproject.toml for CPython 3.11 on x86-64 Linux.  `make lock` rewrites it (keeping the pinned versions
# where they still resolve; `make lock LOCK_ARGS=--upgrade` takes the newest).
LOCK      ?= requirements/lock.txt
UV_SPEC   ?= uv==0.13.8
LOCK_ARGS ?=
# torch's version, pinned in the lock; TORCH_SPEC picks its build: the default is the local CPU build
# (2.13.0+cpu) on these machines; on a CUDA machine set TORCH_SPEC to that version's CUDA build.
TORCH_VERSION := 2.13.0
TORCH_SPEC ?= torch==$(TORCH_VERSION)
# Artifact creation times and run ids come from SOURCE_DATE_EPOCH (pipeline/artifacts/lineage.py): pinned, a
# rerun writes the same bytes wherever and whenever it runs.  315532800 = 1980-01-01T00:00:00Z, the
# reproducible-builds convention's floor (the earliest time a ZIP entry can hold).
SOURCE_DATE_EPOCH ?= 315532800

.PHONY: install lock demo test reduced paper clean-artifacts review-e2e

install: $(VENV)/.installed

# torch through pip (its configured indexes and links pick the build: TORCH_SPEC); the rest of the lock
# through uv, which installs the same pins in parallel, in a fraction of pip's time; then the bytecode of
# the installed packages, compiled once on all cores.  Without it every process compiles what it imports,
# each time, where PYTHONDONTWRITEBYTECODE is set (it is on these machines): +1.8 s per process for torch
# alone (docs/environment.md).  Left out: packages' own tests and torch's one file written for Python 3.12.
SITE_PACKAGES = $$($(BIN)/python -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
$(VENV)/.installed: pyproject.toml Makefile $(LOCK)
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q -c $(LOCK) "$(UV_SPEC)"
	$(BIN)/python -m pip install -q --no-compile -c $(LOCK) "$(TORCH_SPEC)"
	$(BIN)/uv pip install -q --python $(BIN)/python -c $(LOCK) -e ".[dev,sam3]"
	$(BIN)/python -m compileall -q -j 0 -x '/tests?/|/py312_' $(SITE_PACKAGES) >/dev/null \
	  || echo "some installed files did not compile to bytecode; Python compiles them when imported"
	touch $@

# Re-resolve the lock from pyproject.toml (+ torch==$(TORCH_VERSION)) with uv; then `make test`.
lock:
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q "$(UV_SPEC)"
	echo "torch==$(TORCH_VERSION)" | $(BIN)/uv pip compile pyproject.toml - --extra dev --extra sam3 \
	  --python-version 3.11 --python-platform x86_64-manylinux_2_28 --custom-compile-command "make lock" \
	  $(LOCK_ARGS) -o $(LOCK)

demo: install
	$(BIN)/geodistill dag --check
	SOURCE_DATE_EPOCH=$(SOURCE_DATE_EPOCH) PATH="$(CURDIR)/$(BIN):$$PATH" dvc repro

# Another profile: rewrite params.yaml (and check dvc.yaml), then run the DAG with `geodistill run`:
# stale stages as Ray tasks (the teacher on a GPU, several training runs per GPU, CPU stages on cores),
# each one `dvc repro --single-item`, so DVC records it and `dvc repro` afterwards does nothing.  Options
# through RUN_ARGS, e.g. make paper RUN_ARGS="--train-gpu-fraction 0.125"  (see `geodistill run --help`,
# docs/scaling.md).
RUN_ARGS ?=
reduced paper: install
	$(BIN)/geodistill profile $@
	$(BIN)/geodistill dag --check
	SOURCE_DATE_EPOCH=$(SOURCE_DATE_EPOCH) $(BIN)/geodistill run $(RUN_ARGS)

test: install
	$(BIN)/ruff check
	$(BIN)/python -m pytest -q

clean-artifacts:
	rm -rf artifacts reports/demo

# Opt-in, never in CI: the Label Studio review loop against a real server (tools/review_e2e.py):
# upload through the API with the Local files storage, every image URL fetched, a drawn anti-aliased
# brush correction back through review import.  label-studio installs into its own venv (it pins
# packages of its own), at the version last checked (docs/review.md); REVIEW_E2E_ARGS may name a review
# export folder (--review DIR), else a synthetic export goes through.
LS_VENV ?= .cache/label-studio-venv
LS_VERSION ?= 1.23.2
review-e2e:
	test -x $(LS_VENV)/bin/label-studio || ($(PYTHON) -m venv $(LS_VENV) && $(LS_VENV)/bin/pip install -q label-studio==$(LS_VERSION))
	$(BIN)/python -m tools.review_e2e --label-studio $(LS_VENV)/bin/label-studio $(REVIEW_E2E_ARGS)
