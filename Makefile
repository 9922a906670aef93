# Two entry points for a fresh Debian machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test lint bench system-deps gateway clean

# System libraries a fresh Debian lacks: libusb for open3d/pyrealsense2, mosquitto and chromium
# (with its matching chromium-driver) for the tests, faketime (libfaketime) for the test that
# steps the daemon's wall clock.
system-deps:
	@missing=""; \
	ldconfig -p | grep -q 'libusb-1.0.so.0' || missing="$$missing libusb-1.0-0"; \
	command -v mosquitto >/dev/null 2>&1 || [ -x /usr/sbin/mosquitto ] || missing="$$missing mosquitto"; \
	[ -x /usr/bin/chromium ] || missing="$$missing chromium"; \
	[ -x /usr/bin/chromedriver ] || missing="$$missing chromium-driver"; \
	ls /usr/lib/*/faketime/libfaketime.so.1 >/dev/null 2>&1 || missing="$$missing faketime"; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing:$$missing"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing; \
	  else \
	    echo "missing system packages, run: sudo apt-get install$$missing"; exit 1; \
	  fi; \
	fi

$(STAMP): pyproject.toml | system-deps
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[test,bench]'
	$(PY) -m pip install -q --no-deps 'pysparkplug==0.6.1'   # test-only Sparkplug decoder
	touch $(STAMP)

# A gateway: the service and its own library only (libusb for the cameras; no test tools,
# no browser), into the same .venv the systemd unit runs from.
gateway:
	@ldconfig -p | grep -q 'libusb-1.0.so.0' || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0; \
	  else echo "missing system package, run: sudo apt-get install libusb-1.0-0"; exit 1; fi; }
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q .

demo: system-deps $(STAMP)
	$(VENV)/bin/silo-agent run --config config/demo.toml --scans 1

test: system-deps $(STAMP)
	$(VENV)/bin/ruff check silo_agent tests bench
	$(VENV)/bin/ruff format --check silo_agent tests bench
	$(VENV)/bin/mypy
	$(PY) -m pytest -q -n 2 --dist loadfile

# The surveyor's tool the benchmarks compare against (Debian's cloudcompare, run headless).
bench: $(STAMP)
	@command -v CloudCompare >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq cloudcompare; \
	  else echo "missing system package, run: sudo apt-get install cloudcompare"; exit 1; fi; }
	$(PY) bench/accuracy.py
	$(PY) bench/speed.py

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
