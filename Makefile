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

test: $(STAMP)
	$(PY) -m pytest -q

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache demo_out

bench: $(STAMP)
	$(PY) -m rgbd_gt bench
	$(PY) benchmarks/export_depth.py
	$(PY) benchmarks/init_pose.py
	$(PY) benchmarks/load_large_scan.py
	$(PY) benchmarks/trust.py
	$(PY) benchmarks/lidar.py
	$(PY) -m rgbd_gt.bench.verticals
	$(PY) benchmarks/intrinsics.py
	$(PY) benchmarks/big_photo.py
	$(PY) benchmarks/scale.py
	$(PY) -m rgbd_gt.bench.fuzz --trials 600 --seed 1 --root bench_out/fuzz --quiet --report docs/reliability.md
