# Photos → textured mesh with DVR.  `make setup` once, then `make reconstruct IMAGES=dir`.
PY      ?= .venv/bin/python
IMAGES  ?=
MASKS   ?=
CONFIG  ?= configs/default.yaml
OUT     ?=
WS      ?= $(OUT)
FORCE   ?=
ARGS    ?=

.PHONY: setup setup-web test test-fast board synth cameras masks depth train mesh texture report bench-core bench bench-quick reconstruct

# everything: the Python environment, and the report's 3-D viewer (model-viewer) where npm exists
setup: .venv/.installed
	@if command -v npm >/dev/null 2>&1; then $(MAKE) --no-print-directory setup-web \
	  || echo "setup: npm install failed: reports will have no 3-D viewer (retry with make setup-web)"; \
	else echo "setup: npm not found: reports will have no 3-D viewer (install Node.js, then make setup-web)"; fi
.venv/.installed: requirements.txt pyproject.toml
	python3 -m venv .venv
	.venv/bin/pip install -q --upgrade pip
	.venv/bin/pip install -q torch==2.13.0
	.venv/bin/pip install -q -r requirements.txt
	.venv/bin/pip install -q --no-deps --no-build-isolation -e .
	touch $@

# test-time web tools (glTF validator) from npm; the tests that need them skip without node
setup-web: node_modules/.installed
node_modules/.installed: package.json
	npm install --no-audit --no-fund
	touch $@

test: setup
	$(PY) -m pytest -q

test-fast: setup
	$(PY) -m pytest -q -m "not slow"

# a printable ChArUco board for metric scale (A4, 300 dpi): make board [BOARD=board.png]
BOARD ?= board.png
board: setup
	$(PY) -m pipeline board "$(BOARD)"

# synthetic scene: make synth SCENE=configs/scenes/torus.yaml OUT=work/torus
SCENE ?= configs/scenes/torus.yaml
synth: setup
	$(PY) -m pipeline synth "$(SCENE)" "$(OUT)"

cameras: setup
	$(PY) -m pipeline cameras "$(WS)" --images "$(IMAGES)" --config "$(CONFIG)" $(if $(FORCE),--force) $(ARGS)

masks: setup
	$(PY) -m pipeline masks "$(WS)" $(if $(MASKS),--masks "$(MASKS)") --config "$(CONFIG)" $(if $(FORCE),--force) $(ARGS)

depth: setup
	$(PY) -m pipeline depth "$(WS)" --config "$(CONFIG)" $(if $(FORCE),--force) $(ARGS)

train: setup
	$(PY) -m pipeline train "$(WS)" --config "$(CONFIG)" $(if $(FORCE),--force) $(ARGS)

mesh: setup
	$(PY) -m pipeline mesh "$(WS)" --config "$(CONFIG)" $(if $(FORCE),--force) $(ARGS)

texture: setup
	$(PY) -m pipeline texture "$(WS)" --config "$(CONFIG)" $(if $(FORCE),--force) $(ARGS)

report: setup
	$(PY) -m pipeline report "$(WS)"

bench-core: setup
	$(PY) bench/core.py

bench: setup
	$(PY) bench/run.py --readme

bench-quick: setup
	$(PY) bench/run.py --quick

# every stage in order; each is skipped when up to date, and a killed run resumes where it stopped.
# Paths may hold spaces (IMAGES="photos of my vase"): they are quoted, and the default OUT is work/<folder name>.
reconstruct: setup
	@images="$(IMAGES)"; out="$(OUT)"; masks="$(MASKS)"; \
	if [ -z "$$out" ] && [ -n "$$images" ]; then out="work/$$(basename "$$images")"; fi; \
	if [ -z "$$out" ] || { [ -z "$$images" ] && [ ! -f "$$out/cameras.npz" ]; }; then \
	  echo "usage: make reconstruct IMAGES=photos [MASKS=dir] [OUT=workspace] [CONFIG=file]"; exit 2; fi; \
	set -e; \
	if [ -n "$$images" ]; then $(PY) -m pipeline cameras "$$out" --images "$$images" --config "$(CONFIG)"; fi; \
	if [ -n "$$masks" ]; then $(PY) -m pipeline masks "$$out" --masks "$$masks" --config "$(CONFIG)"; \
	elif [ -n "$$images" ]; then $(PY) -m pipeline masks "$$out" --config "$(CONFIG)"; fi; \
	if [ -n "$$images" ]; then $(PY) -m pipeline depth "$$out" --config "$(CONFIG)"; fi; \
	$(PY) -m pipeline train "$$out" --config "$(CONFIG)"; \
	$(PY) -m pipeline mesh "$$out" --config "$(CONFIG)"; \
	$(PY) -m pipeline texture "$$out" --config "$(CONFIG)"; \
	$(PY) -m pipeline report "$$out"; \
	echo "done: $$out/mesh/textured.glb  report: $$out/report.html"
