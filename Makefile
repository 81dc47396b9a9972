# roomcap — the commands a newcomer needs. Everything runs inside $(VENV).
VENV ?= .venv
PY := $(VENV)/bin/python
SHARED ?= $(abspath ../shared)
export ROOMCAP_SHARED := $(SHARED)

# `make calibrate` inputs (defaults: the caliscope ChArUco recording in ../shared)
RECORDING ?= $(SHARED)/data/caliscope/charuco_calibration/calibration/extrinsic
BOARD ?= $(SHARED)/data/caliscope/charuco_calibration/charuco.toml
OUT ?= out/calibration/rig.toml
# `make demo` input: the Pose2Sim multi-person demo
DEMO ?= $(SHARED)/data/pose2sim/demo-wheel-0.10.49/Demo_MultiPerson
DEMO_OUT ?= out/demo

.PHONY: install test test-fast demo calibrate bench lint clean

STAMP := $(VENV)/.installed

$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q -c constraints.txt -e '.[dev,cluster,bench,c3d,opensim,view,stream,rerun]'
	touch $(STAMP)

install: $(STAMP)

test: $(STAMP)
	$(PY) -m pytest -n 2 --dist loadgroup -q

test-fast: $(STAMP)
	$(PY) -m pytest -n 2 --dist loadgroup -q -m "not slow"

demo: $(STAMP)
	$(PY) -m roomcap.pipeline.demo --recording $(DEMO) --out $(DEMO_OUT)

calibrate: $(STAMP)
	$(VENV)/bin/calibrate-run calibrate $(RECORDING) --board $(BOARD) --out $(OUT)

bench: $(STAMP)
	$(PY) -m pip install -q --no-deps 'aniposelib==0.8.0'
	@for b in bench/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	@# mypy does not follow setuptools' editable finder: it sees the checkout as `roomcap` through a link
	mkdir -p $(VENV)/typecheck && ln -sfn $(CURDIR) $(VENV)/typecheck/roomcap
	MYPYPATH=$(VENV)/typecheck $(VENV)/bin/mypy
	$(VENV)/bin/lint-imports

clean:
	rm -rf out .pytest_cache
