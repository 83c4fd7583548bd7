# walker-slam: `make demo` and `make test` do everything on a fresh machine.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp
LIVE_STAMP := $(VENV)/.installed-live-stamp

# Debian packages the live-path tests need: the AVR toolchain for the firmware, simavr
# to run it, libfreenect (the Python binding builds against it; fakenect replays).
DEB_PACKAGES := gcc-avr avr-libc binutils-avr simavr libsimavr-dev libelf-dev \
                libfreenect-dev libfreenect-bin pkg-config

.PHONY: install install-live system-deps firmware demo test test-fast bench lint format clean

# pip compiles the installed modules to bytecode one at a time (half of the install);
# compileall does the same on every core.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet --no-compile -e '.[dev]'
	$(PY) -m compileall -q -j 0 "$$($(PY) -c 'import sysconfig; print(sysconfig.get_path("purelib"))')" \
	  || echo "compileall: the modules above did not compile (pip would have skipped them too)"
	touch $(STAMP)

install: $(STAMP)

# Installs the Debian packages that are missing (as root, or through sudo).
system-deps:
	@missing=""; for p in $(DEB_PACKAGES); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "install ok installed" || missing="$$missing $$p"; \
	done; \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages:$$missing"; \
	  if [ "$$(id -u)" = 0 ]; then sudo=""; else sudo="sudo"; fi; \
	  $$sudo apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive $$sudo apt-get install -y -qq --no-install-recommends $$missing; \
	fi

$(LIVE_STAMP): $(STAMP) | system-deps
	$(PY) -m pip install --quiet -e '.[dev,kinect,realsense]'
	touch $(LIVE_STAMP)

install-live: system-deps $(LIVE_STAMP)

# The board firmware (hardware/firmware/build/walker_board.elf, .hex) and its simavr host.
firmware: system-deps
	$(MAKE) -C hardware/firmware

demo: install
	$(VENV)/bin/walkerslam demo --out out/demo

# The tests start many Python processes (test workers, the CLI, the simulated walker,
# Ray's workers): with PYTHONDONTWRITEBYTECODE set in the environment, each would compile
# the project's modules from source again (collecting the tests: 10 s instead of 4).
TEST_ENV = PYTHONDONTWRITEBYTECODE=
# One test worker per core and one more: the live tests pace the simulated walker in real
# time and leave part of their core idle (the fault test: 21 s of CPU in 30 s), as do the
# tests that wait on the CLI's processes. On 2 cores the suite took 338 s with 2 workers
# and 288 s with 3; with two busy loops beside it, 645 s against 513 s; fresh clones (a
# cold numba cache, which each worker compiles) within their spread (BENCHMARKS.md).
TEST_WORKERS ?= $(shell echo $$(( $$(nproc) + 1 )))

test: install-live firmware
	$(TEST_ENV) $(PY) -m pytest -q -n $(TEST_WORKERS) --durations=25

test-fast: install-live firmware
	$(TEST_ENV) $(PY) -m pytest -q -n $(TEST_WORKERS) -m "not slow"

bench: install-live firmware
	$(PY) benchmarks/run_all.py

lint: install
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .

format: install
	$(PY) -m ruff format .
	$(PY) -m ruff check --fix .

clean:
	rm -rf $(VENV) out build *.egg-info .pytest_cache .ruff_cache hardware/firmware/build
