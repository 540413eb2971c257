# Photos → textured mesh with DVR.  `make setup` once, then `make reconstruct IMAGES=dir`.
PY      ?= .venv/bin/python
IMAGES  ?=
MASKS   ?=
CONFIG  ?= configs/default.yaml
OUT     ?= work/$(notdir $(abspath $(IMAGES)))
WS      ?= $(OUT)
FORCE   ?=
ARGS    ?=

.PHONY: setup setup-web test test-fast synth cameras masks depth train mesh texture report bench-core bench bench-quick reconstruct

setup: .venv/.installed
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

# synthetic scene: make synth SCENE=configs/scenes/torus.yaml OUT=work/torus
SCENE ?= configs/scenes/torus.yaml
synth: setup
	$(PY) -m pipeline synth $(SCENE) $(OUT)

cameras: setup
	$(PY) -m pipeline cameras $(WS) --images $(IMAGES) --config $(CONFIG) $(if $(FORCE),--force) $(ARGS)

masks: setup
	$(PY) -m pipeline masks $(WS) $(if $(MASKS),--masks $(MASKS)) --config $(CONFIG) $(if $(FORCE),--force) $(ARGS)

depth: setup
	$(PY) -m pipeline depth $(WS) --config $(CONFIG) $(if $(FORCE),--force) $(ARGS)

train: setup
	$(PY) -m pipeline train $(WS) --config $(CONFIG) $(if $(FORCE),--force) $(ARGS)

mesh: setup
	$(PY) -m pipeline mesh $(WS) --config $(CONFIG) $(if $(FORCE),--force) $(ARGS)

texture: setup
	$(PY) -m pipeline texture $(WS) --config $(CONFIG) $(if $(FORCE),--force) $(ARGS)

report: setup
	$(PY) -m pipeline report $(WS)

bench-core: setup
	$(PY) bench/core.py

bench: setup
	$(PY) bench/run.py --readme

bench-quick: setup
	$(PY) bench/run.py --quick

# every stage in order; each is skipped when up to date, and a killed run resumes where it stopped
reconstruct: setup
	@if [ -z "$(IMAGES)" ] && [ ! -f "$(OUT)/cameras.npz" ]; then \
	  echo "usage: make reconstruct IMAGES=photos [MASKS=dir] [OUT=workspace] [CONFIG=file]"; exit 2; fi
	$(if $(IMAGES),$(PY) -m pipeline cameras $(OUT) --images $(IMAGES) --config $(CONFIG))
	$(if $(or $(IMAGES),$(MASKS)),$(PY) -m pipeline masks $(OUT) $(if $(MASKS),--masks $(MASKS)) --config $(CONFIG))
	$(if $(IMAGES),$(PY) -m pipeline depth $(OUT) --config $(CONFIG))
	$(PY) -m pipeline train $(OUT) --config $(CONFIG)
	$(PY) -m pipeline mesh $(OUT) --config $(CONFIG)
	$(PY) -m pipeline texture $(OUT) --config $(CONFIG)
	$(PY) -m pipeline report $(OUT)
	@echo "done: $(OUT)/mesh/textured.glb  report: $(OUT)/report.html"
