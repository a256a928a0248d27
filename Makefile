# Two commands do everything on a fresh machine with Python 3.11 and pip:
#   make demo   - the main job (end-to-end demo on the simulated flight)
#   make test   - the test suite (what CI runs)
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
# torch==2.13.0 is the CPU build on these machines; an unpinned torch pulls a multi-GB CUDA build.
TORCH_PIN ?= torch==2.13.0
OUT    ?= out

.PHONY: venv demo demo-full test test-slow lint bench clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet $(TORCH_PIN)
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	OMP_WAIT_POLICY=PASSIVE $(VENV)/bin/uavsim demo --quick --out $(OUT)/demo

demo-full: $(STAMP)
	OMP_WAIT_POLICY=PASSIVE $(VENV)/bin/uavsim demo --out $(OUT)/demo-full

test: $(STAMP)
	OMP_WAIT_POLICY=PASSIVE $(PY) -m pytest -q

test-slow: $(STAMP)
	OMP_WAIT_POLICY=PASSIVE $(PY) -m pytest -q -m slow

lint: $(STAMP)
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(VENV) $(OUT)
