# Everything a person runs. `make demo` and `make test` set up the virtual environment first.
VENV ?= .venv
PYTHON ?= python3
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp
# The index torch comes from, passed to pip as --extra-index-url when set. Empty (the default): pip's own
# configuration, as for every other package; from PyPI on Linux x86_64 that is torch's CUDA build (about 20 nvidia-*
# packages, several GB), which uses an NVIDIA GPU where there is one and runs on the CPU where there is none.
# The CPU-only build: make install TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu
TORCH_INDEX_URL ?=

.PHONY: install demo test test-slow lint type bench docs notebooks clean

$(STAMP): pyproject.toml study/pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -c constraints.txt torch $(if $(TORCH_INDEX_URL),--extra-index-url $(TORCH_INDEX_URL))
	$(PY) -m pip install --quiet -c constraints.txt -e ".[extra,zoo,plots,dev,docs]" -e "./study[distributed,dev]"
	touch $(STAMP)

install: $(STAMP)

# The main job: SERASAC against stock SAC on a small task, a table and a learning-curve plot
demo: install
	$(VENV)/bin/sb3-sera compare

# The test suite without the long learning checks (what CI runs): the library's (tests/) and the study's
# (study/tests/), in TEST_WORKERS pytest-xdist processes with one
# torch thread each (tests/conftest.py); TEST_WORKERS=0 runs it in this process, with torch's default threads. The tests
# of one compiled step share a group (tests/helpers.py), run by one worker in turn: the first compiles, the rest hit
# Inductor's cache
TEST_WORKERS ?= 2
test: install
	$(PY) -m pytest -m "not slow" -n $(TEST_WORKERS) --dist loadgroup

test-slow: install
	$(PY) -m pytest -m slow

lint: install
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .

type: install
	$(PY) -m mypy

bench: install
	$(PY) benchmarks/train_speed.py

# The documentation site, offline, with every warning an error and every cross-reference checked (nitpicky)
docs: install
	$(PY) -m sphinx -W --keep-going -n -b html docs docs/_build/html
	@echo "Open docs/_build/html/index.html"

# The notebooks run again on the ledger, their outputs (tables, figures) saved into them to read in Jupyter or on GitHub
notebooks: install
	$(VENV)/bin/jupyter-execute --inplace notebooks/*.ipynb

clean:
	rm -rf $(VENV) logs build docs/_build *.egg-info study/*.egg-info .pytest_cache .mypy_cache .ruff_cache
