# Each target sets itself up on a fresh machine; the stamp makes a second run start in seconds.
VENV  := .venv
PY    := $(VENV)/bin/python
STAMP := $(VENV)/.rgbd-gt-installed
DATA  := ../shared/data

.PHONY: setup demo test bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml scripts/setup.sh
	@bash scripts/setup.sh
	@touch $@

demo: $(STAMP)
	@bash scripts/demo.sh

# on every core (pytest-xdist; tests/conftest.py shares the cores out): 10-14 min on 2 cores (the machine's day decides)
test: $(STAMP)
	$(PY) -m pytest -q -n auto --dist worksteal

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache demo_out

bench: $(STAMP)
	$(PY) -m benchmarks --out docs
