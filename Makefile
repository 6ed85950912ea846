# Small entry points; every target works on a fresh machine (Python 3.11 + pip).
PYTHON ?= python3

.PHONY: demo install test check lint bench

## Set up and fly the paper's tracking scenario on four emulated PX4 vehicles through MAVSDK
## (summary, figures and MAVLink logs in out/paper_tracking_flyable/).
demo: install
	mission-runner run configs/paper_tracking_flyable.yaml --out out/paper_tracking_flyable

install:
	$(PYTHON) -m pip install --quiet -e ".[test]"

## Set up (package, test tools, mosquitto if missing and we are root) and run every test.
test: install
	@command -v mosquitto >/dev/null 2>&1 || command -v /usr/sbin/mosquitto >/dev/null 2>&1 || \
	  { if [ "$$(id -u)" = 0 ]; then \
	      (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq mosquitto) >/dev/null; \
	    else echo "mosquitto missing: install it (e.g. sudo apt-get install mosquitto)"; exit 1; fi; }
	$(PYTHON) -m ruff check .
	$(PYTHON) -m ruff format --check .
	$(PYTHON) -m mypy
	lint-imports
	$(PYTHON) -m pytest

## The fast lane while developing: lint, types and every test that flies nothing, needs no broker
## and is not marked slow, on two pytest workers (pytest-xdist; benchmarks off, as xdist turns
## them off with a warning). `make test` (what CI runs) adds the rest, on one. Measured with
## `/usr/bin/time make -o install check`, mypy's cache warm, on 2 shared cores: 2026-12-05 quiet
## (load 0.2-1.2), 1216 tests: 52.8 s wall, 74 s CPU (user+sys); the target is 60 s. Before
## plumbing tests ran on tiny scenarios and statistical batches went slow: 138 s CPU, 90 s wall.
## Each worker spends 9 s CPU collecting where PYTHONDONTWRITEBYTECODE is set (3.5 s with a
## bytecode cache). --dist load kept: worksteal, loadscope, loadfile and -n 3 measured no better.
## The fast lane's tests on one worker (`python -m pytest -q -m "not slow and not mavsdk and not
## mqtt" -n 0`, load 2.7-4.6): 84 s CPU, 109 s wall.
check: install
	$(PYTHON) -m ruff check .
	$(PYTHON) -m ruff format --check .
	$(PYTHON) -m mypy
	lint-imports
	$(PYTHON) -m pytest -q -n 2 --benchmark-disable -m "not slow and not mavsdk and not mqtt"

lint:
	$(PYTHON) -m ruff check .
	$(PYTHON) -m ruff format --check .
	$(PYTHON) -m mypy
	lint-imports

## The headline figures (demo wall time, vehicle-process CPU, 1x lateness, swarm size, simulator),
## printed and written to out/bench/headline.json (about 6 minutes on 2 cores).
bench: install
	$(PYTHON) bench/headline.py
