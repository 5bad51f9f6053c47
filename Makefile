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
	@# the interactive map's test opens it in Debian's headless Chromium, offline
	@command -v chromium >/dev/null 2>&1 || { \
	  echo "installing Debian's chromium (the browser test of the HTML maps)"; \
	  SUDO=$$([ "$$(id -u)" = 0 ] || echo sudo); \
	  $$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq chromium; }
	@# gdal-bin's gdalinfo checks the COG layout of prior.tif in the tests (an independent GDAL build).
	@dpkg -s gdal-bin >/dev/null 2>&1 || { \
	  echo "installing Debian's gdal-bin (gdalinfo, for the COG tests)"; \
	  SUDO=$$([ "$$(id -u)" = 0 ] || echo sudo); \
	  $$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq gdal-bin; }
	test -d $(VENV) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[dev,lidar]"
	touch $(STAMP)

prior: setup
	$(VENV)/bin/terrain-prior build terrain_data/region.toml --out $(OUT)/prior.tif
	$(VENV)/bin/terrain-prior show $(OUT)/prior.tif --png $(OUT)/prior.png --features-png $(OUT)/features.png --html $(OUT)/prior.html

# The main job: the prior and its maps, one simulated data set tracked with TT and drawn, and the
# paper's experiment (28 data sets x 100 reports, UU/UT/TT over a tau grid) with its figures.
demo: prior
	$(VENV)/bin/terrain-track simulate --prior $(OUT)/prior.tif --seed 0 --out $(OUT)/reports.csv --truth-out $(OUT)/targets.csv
	$(VENV)/bin/terrain-track run --prior $(OUT)/prior.tif --reports $(OUT)/reports.csv --variant TT --tau -4.75 --out $(OUT)/tracks.gpkg
	$(VENV)/bin/terrain-track show --prior $(OUT)/prior.tif --reports $(OUT)/reports.csv --tracks $(OUT)/tracks.gpkg --truth $(OUT)/targets.csv --png $(OUT)/tracks.png --html $(OUT)/tracks.html --vector terrain_data/region.gpkg:roads --vector terrain_data/region.gpkg:lakes=water
	$(VENV)/bin/terrain-track experiment --prior $(OUT)/prior.tif --datasets 28 --reports 100 --tau -9:3:0.25 --out $(OUT)/experiment

# One pytest worker per core (pytest-xdist); worksteal evens out the long notebook and CLI tests.
test: setup
	$(PY) -m pytest -q -n auto --dist worksteal

bench: setup
	$(PY) -m bench.run

lint: setup
	$(VENV)/bin/ruff check pipeline tracker tests bench

notebooks: setup
	$(PY) -m notebooks.run

clean:
	rm -rf $(OUT) .pytest_cache
