# Every target depends on setup, so each works alone on a fresh clone.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
OUT ?= out

.PHONY: setup demo prior test bench lint notebooks clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	@# open3d's wheel links against libusb; Debian ships it as libusb-1.0-0.
	@dpkg -s libusb-1.0-0 >/dev/null 2>&1 || { \
	  echo "installing Debian's libusb-1.0-0 (needed by open3d)"; \
	  SUDO=$$([ "$$(id -u)" = 0 ] || echo sudo); \
	  $$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq libusb-1.0-0; }
	test -d $(VENV) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[dev,lidar]"
	touch $(STAMP)

prior: setup
	$(VENV)/bin/terrain-prior build terrain_data/region.toml --out $(OUT)/prior.tif
	$(VENV)/bin/terrain-prior show $(OUT)/prior.tif --png $(OUT)/prior.png --features-png $(OUT)/features.png

demo: prior

test: setup
	$(PY) -m pytest -q

bench: setup
	$(PY) -m bench.run

lint: setup
	$(VENV)/bin/ruff check pipeline tracker tests bench

notebooks: setup
	$(PY) -m notebooks.run

clean:
	rm -rf $(OUT) .pytest_cache
