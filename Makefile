# RMMDet: every target installs what it needs on first use (a fresh machine needs only `make up` / `make test`).
SHELL := /bin/bash
.DEFAULT_GOAL := help

PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
INSTALLED := $(VENV)/.installed
PROTO_SRC := $(wildcard proto/rmmdet/v1/*.proto)
PROTO_STAMP := proto/gen/.stamp
SUPERVISOR_CONF := deploy/local/supervisord.conf
RUN_DIR := .run
PYTEST_ARGS ?=

.PHONY: help install proto pki up down status logs view-web screenshots docs test test-unit test-integration test-fault bench soak models eval eval-fusion eval-real eval-robustness experiments experiments-city experiments-cities lint typecheck fmt clean

help: ## list targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-18s %s\n", $$1, $$2}'

$(INSTALLED): pyproject.toml
	@command -v $(PYTHON) >/dev/null || { echo "error: $(PYTHON) not found (PyBullet 3.2.7 needs CPython 3.11)"; exit 1; }
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check --upgrade pip
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -e '.[dev,train]'
	@# TrackEval (HOTA) declares opencv-python, whose cv2 would overwrite opencv-python-headless's:
	@# installed alone; numpy, scipy and tabulate, all it imports, come with the project (pyproject.toml).
	$(BIN)/python -m pip install --quiet --disable-pip-version-check --no-deps trackeval==1.3.0
	@# System packages pip cannot provide: libusb-1.0 (open3d's wheel links it); for the tests, Debian's
	@# chromium (the dashboard test's browser), nftables and iproute2 (the multi-host tests' network
	@# namespaces and cut links). Installed with apt when root, else named and the install stops.
	@missing=""; \
	ldconfig -p | grep -q 'libusb-1.0.so.0' || missing="$$missing libusb-1.0-0"; \
	command -v chromium >/dev/null || missing="$$missing chromium"; \
	command -v nft >/dev/null || missing="$$missing nftables"; \
	command -v ip >/dev/null || missing="$$missing iproute2"; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    DEBIAN_FRONTEND=noninteractive apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing; \
	  else echo "error: system packages missing:$$missing (as root: apt-get install$$missing)"; exit 1; fi; \
	fi
	@touch $@

install: $(INSTALLED) $(PROTO_STAMP) ## create .venv and install the project (+ dev tools), generate protobuf code

$(PROTO_STAMP): $(INSTALLED) $(PROTO_SRC) proto/generate.py
	$(BIN)/python proto/generate.py

proto: $(INSTALLED) ## (re)generate the protobuf Python code into proto/gen
	$(BIN)/python proto/generate.py

# Profiles (deploy/profiles/, composed by shared/supervision/profiles.py): base.yaml with one overlay per
# variable. SCENE: deploy/profiles/scene/<SCENE>.yaml, or any deploy/scenes/<SCENE>.yaml. SENSORS=sim: the
# sim's sensor groups publish their frames; SENSORS=wire: they emulate the site file's devices on the wire
# (Robosense UDP, ARS 408 CAN over slcan, MJPEG over HTTP) and the device services read them onto the bus.
# SHARDS=N > 1: the coordinator as N region shards over the scene's region map of N regions. SITE: another
# device site file. SPEED: sim seconds per wall second. `make up` renders the programs and the services'
# settings into .run/profile/ (deploy/local/supervisord.conf includes the programs).
WORLD ?= table
SCENARIO ?= tests/fixtures/real/sumo_scenarios/bologna_pasubio/run.sumocfg
SCENE ?= $(if $(filter city,$(WORLD)),city,sand_table)
SENSORS ?= sim
SHARDS ?= 1
SITE ?=
SPEED ?=
PROFILE_ARGS = --scene $(SCENE) --sensors $(SENSORS) --shards $(SHARDS) $(if $(SITE),--site $(SITE)) $(if $(SPEED),--set settings.sim.overrides.speed=$(SPEED))

up: install pki ## start router and every service under supervisord (idempotent); SCENE=name; SENSORS=wire: through emulated devices and the device services; SHARDS=2: the coordinator as two region shards; SPEED=x: sim seconds per wall second; WORLD=city SCENARIO=RUN.sumocfg [CITY_SCALE=k]: a SUMO scenario as the world (services/city), its demand scaled k times
	@mkdir -p $(RUN_DIR)/logs
	@if $(BIN)/supervisorctl -c $(SUPERVISOR_CONF) pid >/dev/null 2>&1; then \
	  echo "already up (make down first to change the profile)"; \
	else \
	  $(if $(filter city,$(SCENE)),$(BIN)/python -m services.city prepare --scenario $(SCENARIO) --scale $(or $(CITY_SCALE),1) --work $(RUN_DIR)/city && )$(BIN)/python -m shared.supervision.profiles $(PROFILE_ARGS) && \
	  $(BIN)/supervisord -c $(SUPERVISOR_CONF) && echo "supervisord started"; \
	fi
	@$(BIN)/python -m services.cli.main wait-ready --timeout 30
	@$(BIN)/supervisorctl -c $(SUPERVISOR_CONF) status || true
	@echo "try: $(BIN)/rmmdet topics   |   $(BIN)/rmmdet health   |   make down"

pki: install ## local CA, service certificates and plan-signing key in .run/pki (keeps what exists)
	@$(BIN)/rmmdet pki init --shards $(SHARDS)

down: ## stop every service and supervisord; leaves no process behind
	@if [ -x $(BIN)/python ]; then $(BIN)/python deploy/local/down.py --conf $(SUPERVISOR_CONF); else echo "not installed: nothing to stop"; fi

docs: install ## the documentation site (MkDocs + Material, strict: a broken link fails) -> site/
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --site-dir site

status: ## supervisor view of the services
	@$(BIN)/supervisorctl -c $(SUPERVISOR_CONF) status || true

logs: ## tail all service logs
	@tail -n 50 -F $(RUN_DIR)/logs/*.log

VIEW_WEB_PORT ?= $(shell $(BIN)/python -c "from shared.viewer.origin import VIEW_WEB_PORT; print(VIEW_WEB_PORT)")
view-web: install ## the live 3D view in a local browser: prebuilt Foxglove Studio (from npm; needs npm) on http://127.0.0.1:VIEW_WEB_PORT/ (shared/viewer/origin.py), connected to the viewer with the project's layout
	@bash deploy/foxglove/web/assemble.sh $(RUN_DIR)/foxglove-web >/dev/null
	@echo "open http://127.0.0.1:$(VIEW_WEB_PORT)/?ds=foxglove-websocket&ds.url=ws://127.0.0.1:8765   (Ctrl-C stops)"
	@$(BIN)/python -m http.server $(VIEW_WEB_PORT) --bind 127.0.0.1 --directory $(RUN_DIR)/foxglove-web

screenshots: install ## with `make up` running: the dashboard and the 3D view in headless Chromium -> docs/images/{dashboard_live,view3d}.png
	$(BIN)/python -m tests.bench.screenshots

test: install pki ## lint, type-check, then unit + integration + fault tests (excludes slow experiments)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy
	@# Not --quiet: it hides the warnings strict mode fails on. The log is shown only when the build fails.
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --site-dir $(RUN_DIR)/site >$(RUN_DIR)/mkdocs.log 2>&1 || { grep -v '^INFO' $(RUN_DIR)/mkdocs.log; exit 1; }
	$(BIN)/python -m pytest -m "not slow" $(PYTEST_ARGS)

test-unit: install
	$(BIN)/python -m pytest -m "not slow and not integration and not fault" $(PYTEST_ARGS)

test-integration: install
	$(BIN)/python -m pytest -m "integration and not slow" $(PYTEST_ARGS)

test-fault: install
	$(BIN)/python -m pytest -m "fault and not slow" $(PYTEST_ARGS)

bench: install pki ## benchmarks: the whole system as `make up` runs it (10 min), then bus, sim, detectors, MEC, coordinator, memory, secure sites, device decoders, recording import -> tests/bench/results/*.json
	$(MAKE) down
	$(BIN)/python -m tests.bench.system_bench --readme $(SYSTEM_BENCH_ARGS)
	$(BIN)/python -m tests.bench.bus_bench $(BENCH_ARGS)
	$(BIN)/python -m tests.bench.sim_bench $(BENCH_ARGS)
	$(BIN)/python -m tests.bench.camera_detector_bench --model $(MODELS_DIR)/camera/model.onnx $(BENCH_DATA)
	$(BIN)/python -m tests.bench.lidar_detector_bench --model $(MODELS_DIR)/lidar/pointpillars.onnx $(BENCH_DATA)
	$(BIN)/python -m tests.bench.mec_bench
	$(BIN)/python -m tests.bench.coordinator_bench
	$(BIN)/python -m tests.bench.memory_bench --readme
	$(BIN)/python -m tests.bench.sites_bench --readme
	$(BIN)/python -m tests.shared.bus.fuzz --inputs 1000000 --out tests/bench/results/fuzz.json
	$(BIN)/python -m tests.bench.device_decoder_bench
	$(BIN)/python -m tests.shared.devices.fuzz --inputs 1000000 --out tests/bench/results/device_fuzz.json
	$(BIN)/python -m tests.shared.captures.fuzz --inputs 100000 --out tests/bench/results/capture_fuzz.json
	$(BIN)/python -m tests.bench.import_bench

soak: install pki ## the whole system for 1 h: RSS slope (MB/h), threads and fds per process -> tests/bench/results/system.json (label soak)
	$(MAKE) down
	$(BIN)/python -m tests.bench.system_bench --minutes 60 --label soak

DATASET ?= data/datasets/default
MODEL_RUNS ?= data/models
MODELS_DIR := deploy/models
# Detector benches time real frames of the held-out split when the dataset exists (else simulated ones).
BENCH_DATA = $(if $(wildcard $(DATASET)/manifest.json),--data $(DATASET) --split test,)

models: install ## regenerate the default dataset (per-seed conditions), retrain both detectors from their committed configs (ONNX + card + int8 + metrics; CPU ~2.5 h), evaluate; results in deploy/models
	$(BIN)/python -m studies.dataset.generate --out $(DATASET) --workers 2 --no-progress
	cp $(DATASET)/manifest.json $(MODELS_DIR)/dataset_manifest.json
	mkdir -p $(MODEL_RUNS)
	$(BIN)/rmmdet train camera --data $(DATASET) --out $(MODEL_RUNS)/camera --config $(MODELS_DIR)/camera/config.json > $(MODEL_RUNS)/camera.log 2>&1 || { tail -20 $(MODEL_RUNS)/camera.log; exit 1; }
	cp $(MODEL_RUNS)/camera/model.onnx $(MODEL_RUNS)/camera/model_int8.onnx $(MODEL_RUNS)/camera/model.yaml $(MODEL_RUNS)/camera/config.json $(MODELS_DIR)/camera/
	cp $(MODEL_RUNS)/camera.log $(MODELS_DIR)/camera/train.log
	$(BIN)/rmmdet train lidar --data $(DATASET) --out $(MODEL_RUNS)/lidar --config $(MODELS_DIR)/lidar/pointpillars.json > $(MODEL_RUNS)/lidar.log 2>&1 || { tail -20 $(MODEL_RUNS)/lidar.log; exit 1; }
	cp $(MODEL_RUNS)/lidar/pointpillars.onnx $(MODEL_RUNS)/lidar/pointpillars_int8.onnx $(MODEL_RUNS)/lidar/history.json $(MODELS_DIR)/lidar/
	cp $(MODEL_RUNS)/lidar.log $(MODELS_DIR)/lidar/train.log
	$(MAKE) eval

eval: install ## evaluate every detector on the held-out split -> deploy/models/metrics.json and the README's detector table
	$(BIN)/rmmdet eval detectors --data $(DATASET) --split test --out $(MODELS_DIR)/metrics.json --readme

eval-fusion: install ## calibrated scores fitted on the tuning seeds, then MEC fusion + tracking vs sim ground truth, tuning then held-out seeds (~30 min) -> deploy/mec/score_calibration.json, docs/eval/fusion{_tuning,}
	$(BIN)/rmmdet eval calibrate-scores --workers 2
	$(BIN)/rmmdet eval fusion --split tuning --no-noise --workers 2 --readme
	$(BIN)/rmmdet eval fusion --split test --workers 2 --readme

eval-real: install ## the MEC on the vendored real roadside frames (TUMTraf A9, Rope3D) vs their labels (~1 min) -> docs/eval/real, docs/real-data.md; another dataset: rmmdet eval real --format F --data DIR
	$(BIN)/rmmdet eval real --format openlabel --data tests/fixtures/real/tumtraf_a9 --readme
	$(BIN)/rmmdet eval real --format rope3d --data tests/fixtures/real/rope3d --readme

eval-robustness: install ## fusion accuracy under 2x noise, 100 ms delay, extrinsic error, 32 vehicles vs clean (~30 min) -> docs/eval/robustness
	$(BIN)/rmmdet eval robustness --workers 2 --readme
	$(BIN)/rmmdet eval robustness --radar --workers 2 --readme

experiments: install ## the flow experiment: oracle fitted on real-chain runs, 6 arms x 10/20/40 vehicles x 5 seeds, real chain vs oracle on 3 seeds x 10/20 vehicles (~55 min) -> docs/eval/flow
	$(BIN)/rmmdet experiments flow --out docs/eval/flow --readme

experiments-city: install ## scheduling at scale: a 10x10 SUMO grid, 3 demand levels x 3 coverages x 5 seeds, the coordinator vs the routes as given / shortest paths / SUMO rerouting (about an hour with 2 workers) -> docs/eval/city
	$(BIN)/rmmdet experiments city --out docs/eval/city

experiments-cities: install ## the city study on three public real-city SUMO scenarios (Bologna x2, Hamburg): tuned on one, scored once on the others' held-out seeds -> docs/eval/city-real
	$(BIN)/rmmdet experiments cities --out docs/eval/city-real --readme

lint: install ## ruff
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

fmt: install
	$(BIN)/ruff format .
	$(BIN)/ruff check --fix .

typecheck: install ## mypy on the shared library
	$(BIN)/mypy

clean: down
	rm -rf proto/gen $(RUN_DIR) .pytest_cache .ruff_cache .mypy_cache
