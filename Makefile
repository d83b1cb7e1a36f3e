# bat3r: `make demo` and `make test` work from a fresh clone (they install what they need into .venv).
PYTHON ?= python3.11
VENV := .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip
STAMP := $(VENV)/.bat3r-installed
TORCH_VERSION := 2.13.0
# two test processes (pytest-xdist; one test file per process at a time: module fixtures stay whole)
PYTEST_ARGS ?= -n 2 --dist loadfile --durations=25

.PHONY: install test demo bench bench-demo bench-fidelity server server-stop clean browser-deps system-libs

# pip's own output (warnings included) goes to $(INSTALL_LOG), not the first screen; a failed step prints its tail.
INSTALL_LOG := $(VENV)/install.log
QUIET_PIP = { $(PIP) install --quiet $(1) >>$(INSTALL_LOG) 2>&1 || { tail -n 40 $(INSTALL_LOG); echo "pip install $(1) failed (log: $(INSTALL_LOG))"; exit 1; }; }

$(PY):
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "bat3r needs Python 3.11 ($(PYTHON) not found; set PYTHON=...)"; exit 1; }
	$(PYTHON) -m venv $(VENV)
	@$(call QUIET_PIP,--upgrade pip)

# CPU-only machines take the CPU build of torch first (an unpinned torch would pull multi-GB CUDA wheels);
# machines with an NVIDIA driver let pip resolve torch's default (CUDA) build through the project requirement.
$(STAMP): pyproject.toml | $(PY)
	@if command -v nvidia-smi >/dev/null 2>&1; then \
		echo "NVIDIA GPU found: installing the default torch build"; \
	else \
		echo "no GPU: installing torch==$(TORCH_VERSION) (CPU)"; \
		$(call QUIET_PIP,torch==$(TORCH_VERSION)); \
	fi
	@echo "installing bat3r and its dependencies into $(VENV) (log: $(INSTALL_LOG))"
	@$(call QUIET_PIP,-e ".[test]")
	@touch $(STAMP)

install: $(STAMP) system-libs

# open3d (even the -cpu wheel) links libusb-1.0; Debian's minimal images lack it (needs root or sudo).
system-libs:
	@if ! ldconfig -p 2>/dev/null | grep -q "libusb-1.0.so.0"; then \
		if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then \
			apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null; \
		else echo "error: open3d needs the system library libusb-1.0 (Debian/Ubuntu: apt-get install libusb-1.0-0)"; exit 1; fi; \
	fi

# Headless Chromium for the report/dashboard browser tests (Debian package; needs root or sudo).
browser-deps:
	@if [ ! -x /usr/bin/chromium ]; then \
		if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then \
			(apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) \
			|| echo "warning: could not install chromium; browser tests will be skipped"; \
		else echo "warning: /usr/bin/chromium missing and not root; browser tests will be skipped"; fi; \
	fi

test: install browser-deps
	$(PY) -m pytest $(PYTEST_ARGS)

demo: install
	PREFECT_SERVER_ANALYTICS_ENABLED=false $(PY) flows/demo.py

# Stage benchmarks; the analyses of a finished demo run (control, fit oracle) are `make bench-demo` (after `make demo`:
# rerunning the demo here would reuse its cached stages and could not re-measure it). Its fit diagnosis is recorded
# as fit_oracle_demo: fit_oracle.json is the 2 December record of the paper's recipe that the README cites.
RUN_ANALYSES := benchmarks/bench_demo_control.py benchmarks/bench_fit_oracle.py
bench: install
	@for b in $(filter-out $(RUN_ANALYSES) benchmarks/bench_fidelity.py,$(wildcard benchmarks/bench_*.py)); do \
		echo "== $$b"; $(PY) $$b || exit 1; done

bench-demo: install
	$(PY) benchmarks/bench_demo_control.py --record-as demo_control
	$(PY) benchmarks/bench_fit_oracle.py --record-as fit_oracle_demo

# The loop against its same-compute control and oracle at the catalog's `bench` preset (~55 min on 2 cores;
# resumable: rerun after an interruption), then the fit diagnosis of its Φ₀ predictions. The paper's three ablations
# add ~20 min each: `make bench-fidelity BENCH_FIDELITY_ARGS=--ablations` (~2 h 20 min on 2 cores).
BENCH_FIDELITY_ARGS ?=
BENCH_CATEGORY ?= toy_wide
bench-fidelity: install
	PREFECT_SERVER_ANALYTICS_ENABLED=false $(PY) benchmarks/bench_fidelity.py --category $(BENCH_CATEGORY) --preset bench --run-name bench $(BENCH_FIDELITY_ARGS)
	$(PY) benchmarks/bench_fit_oracle.py --category $(BENCH_CATEGORY) --run-name bench --error-scales 0.25 0.5 --record-as fit_oracle_bench

# A local Prefect server (127.0.0.1), the process work pool, the deployments of deploy/prefect.yaml and a worker.
server: install
	PY=$(abspath $(PY)) bash deploy/server.sh

server-stop:
	PY=$(abspath $(PY)) bash deploy/server-stop.sh

clean:
	rm -rf runs .pytest_cache
