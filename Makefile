# The README's two commands: `make demo` (install + whole DAG on the embedded synthetic benchmark)
# and `make test` (install + test suite).  Everything installs into .venv.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
# The local CPU build of torch; on a CUDA machine set TORCH_SPEC to the CUDA build you want.
TORCH_SPEC ?= torch==2.13.0

.PHONY: install demo test reduced paper clean-artifacts

install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml Makefile
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q "$(TORCH_SPEC)"
	$(BIN)/python -m pip install -q -e ".[dev,sam3]"
	touch $@

demo: install
	$(BIN)/geodistill dag --check
	PATH="$(CURDIR)/$(BIN):$$PATH" dvc repro

# Another profile: rewrite params.yaml (and check dvc.yaml), then run the DAG with `geodistill run`:
# stale stages as Ray tasks (the teacher on a GPU, several training runs per GPU, CPU stages on cores),
# each one `dvc repro --single-item`, so DVC records it and `dvc repro` afterwards does nothing.  Options
# through RUN_ARGS, e.g. make paper RUN_ARGS="--train-gpu-fraction 0.125"  (see `geodistill run --help`,
# docs/scaling.md).
RUN_ARGS ?=
reduced paper: install
	$(BIN)/geodistill profile $@
	$(BIN)/geodistill dag --check
	$(BIN)/geodistill run $(RUN_ARGS)

test: install
	$(BIN)/python -m pytest -q

clean-artifacts:
	rm -rf artifacts reports/demo
