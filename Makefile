# radserve: `make demo` (set-up, then the main job) and `make test` (set-up, then every test).
SHELL := /bin/bash
VENV := .venv
PYTHON := $(VENV)/bin/python
STAMP := $(VENV)/.installed
TORCH_STAMP := $(VENV)/.installed-torch
DIST_STAMP := $(VENV)/.installed-dist
BIN := target/release/radserve
export PYO3_PYTHON := $(abspath $(PYTHON))

.PHONY: setup system-libs build dist demo test test-rust test-python test-learners test-cluster images images-local bench-cluster fuzz soak bench bench-sim bench-augment bench-replay bench-views bench-security bench-demo bench-learning bench-reverb docs-tables preview torch lock proto api-snapshot clean

## setup: system libraries, .venv with the locked Python dependencies and the client, release binary
setup: system-libs $(STAMP) build

system-libs:
	@bash scripts/ensure-system-libs.sh

$(PYTHON):
	python3 -m venv $(VENV)
	$(PYTHON) -m pip install -q --upgrade pip

# pip runs only when a lock file or the client's metadata changed. EnvPool (the engine="envpool" option)
# goes in after the rest without its declared dependencies (requirements-envpool.lock says why).
$(STAMP): requirements.lock requirements-envpool.lock requirements-k8s.lock client-py/pyproject.toml | $(PYTHON)
	$(PYTHON) -m pip install -q -r requirements.lock -r requirements-k8s.lock
	$(PYTHON) -m pip install -q --no-deps -r requirements-envpool.lock
	$(PYTHON) -m pip install -q --no-deps -e client-py
	touch $(STAMP)

build: $(STAMP)
	cargo build --release -p radserve

## demo: a server on localhost and RAD-SAC (translate) learning dm_control's cartpole-swingup from
## pixels through it, with a progress bar (64x64 frames translated to 72x72, a 16-filter encoder,
## batch 32, 40k environment steps, 10 evaluation episodes every 8k; the README's table says how long; docs/learning.md); ends with one line: the
## evaluation return at the start and at the end, the curve runs/demo/<run>/curve.png and the
## augmentation preview grid.
DEMO_ENV ?= dmc/cartpole-swingup
DEMO_FLAGS ?= --env $(DEMO_ENV) --image-size 64 --aug "translate(72)" --num-filters 16 --total-env-steps 40000 \
	--init-steps 125 --batch-size 32 --eval-every 8000 --eval-episodes 10 --render-profile fast --log-every 50
demo: setup torch
	$(PYTHON) client-py/examples/sac_pixels.py $(DEMO_FLAGS) --runs-dir runs/demo
	$(BIN) augment-preview --env $(DEMO_ENV) --out runs/demo/augment-preview.png > /dev/null
	@echo "demo: $$(cat $$(ls -td runs/demo/*/ | head -1)summary.txt); augmentations: runs/demo/augment-preview.png"

## test: every test: clippy, Rust unit and integration tests, the server's end-to-end tests, then (after the
## learners' extra is installed, so the server's tests never wait for torch) the learners' smoke tests
test: setup test-rust test-python test-learners

# clippy first: its findings (warnings are errors) are cheaper to read than a failing test run. The test
# runs are bounded (scripts/bounded.sh): one that hangs ends the run with every process's stacks printed.
# Usually: Rust ~5 min, Python ~5 min on 2 cores.
TEST_BOUND_S ?= 1500
test-rust:
	cargo clippy --release --workspace --all-targets -- -D warnings
	cargo test --release --workspace --no-run
	bash scripts/bounded.sh $(TEST_BOUND_S) cargo test --release --workspace

test-python:
	bash scripts/bounded.sh $(TEST_BOUND_S) $(PYTHON) -m pytest -q tests client-py/tests --ignore=tests/test_learners.py \
		--ignore=tests/test_drq_shift.py \
		--ignore=client-py/tests/test_torch_adapter.py --ignore=tests/cluster

## dist: the release's wheels in dist/: radserve (the client, pure Python) and radserve-server (the
## binary for Linux x86_64 and CPython 3.11, with the simulators as dependencies; maturin, pyproject.toml)
dist: $(STAMP) $(DIST_STAMP)
	rm -rf dist && mkdir dist
	$(PYTHON) -m pip wheel -q --no-deps -w dist ./client-py && rm -rf client-py/build
	$(VENV)/bin/maturin build -q --release --locked --out dist -i $(PYTHON)
	@ls dist

$(DIST_STAMP): requirements-dist.lock | $(PYTHON)
	$(PYTHON) -m pip install -q -r requirements-dist.lock
	touch $(DIST_STAMP)

## images: the server and learner images (radserve:dev, radserve-learner:dev) on public base images;
## images-local: the same on base images made here from Debian packages (no registry needed), the
## learner with PyTorch (the Kubernetes overlays' learner Job trains RAD-SAC in it)
images:
	bash docker/build.sh --with-torch

images-local:
	bash docker/build.sh --local-bases --with-torch

## test-cluster: the container tests (tests/cluster): three server containers and a learner container on
## a private Docker network, one sharded session over them, a server killed, restarted and stopped;
## Compose; the Kubernetes overlays run as written (tests/cluster/test_k8s.py: the dev, tls and
## tls-secret overlays, probes and the learner Job's short run); the wheels installed where there is no
## repository and no Rust. Builds the images and the
## wheels first (on local bases: nothing is pulled). Needs a Docker engine.
test-cluster: setup images-local dist
	$(PYTHON) -m pytest -q -s tests/cluster

test-learners: torch
	RADSERVE_REQUIRE_TORCH=1 bash scripts/bounded.sh $(TEST_BOUND_S) $(PYTHON) -m pytest -q tests/test_learners.py \
		tests/test_drq_shift.py client-py/tests/test_torch_adapter.py

## fuzz: the fuzzing properties of `make test` with many more cases: the pipeline parser and plans,
## the worker protocol's decoder, every RPC of a real server (request sequences and raw bytes), and
## hypothesis through grpcio. Each prints how many cases it ran. FUZZ_SCALE multiplies them all.
FUZZ_SCALE ?= 1
fuzz: setup
	PROPTEST_CASES=$$((200000 * $(FUZZ_SCALE))) cargo test --release -p radserve-augment --test fuzz
	PROPTEST_CASES=$$((200000 * $(FUZZ_SCALE))) cargo test --release -p radserve-sim --test protocol_fuzz
	PROPTEST_CASES=$$((1000 * $(FUZZ_SCALE))) cargo test --release -p radserve --test fuzz -- --nocapture
	RADSERVE_FUZZ_EXAMPLES=$$((1000 * $(FUZZ_SCALE))) $(PYTHON) -m pytest -q -s tests/test_fuzz.py

## soak: bench/soak.py for SOAK_MINUTES (10): clients acting and sampling, killed at random; the
## server's RSS, fds, workers and sessions over time
SOAK_MINUTES ?= 10
soak: setup
	$(PYTHON) bench/soak.py --minutes $(SOAK_MINUTES)

## torch: the learners' extra in .venv (PyTorch, TensorBoard, matplotlib), for the learners, their smoke
## tests and the benchmarks; never needed by the server
torch: $(TORCH_STAMP)

$(TORCH_STAMP): requirements-torch.lock $(STAMP)
	$(PYTHON) -m pip install -q -r requirements-torch.lock
	touch $(TORCH_STAMP)

## bench: every benchmark table (simulator throughput, augmentation kernels vs PyTorch, replay streams,
## what tokens and TLS cost) (the learning checks take hours on two cores: make bench-learning runs them)
bench: bench-sim bench-augment bench-replay bench-views bench-security

## bench-demo: `make demo`, then its run recorded in bench/results/demo.json (the README's demo table)
bench-demo: demo
	$(PYTHON) bench/demo_result.py $$(ls -td runs/demo/*/ | head -1)

## bench-cluster: steps/s and sharded batches/s over 1-3 server containers beside one local server, and
## server-side against learner-side acting over three (bench/cluster_acting.py)
bench-cluster: setup images-local
	$(PYTHON) bench/cluster.py
	$(PYTHON) bench/cluster_acting.py

bench-security: setup
	$(PYTHON) bench/security_overhead.py --rounds 6 --steps 6000 --batches 120

bench-sim: setup
	$(PYTHON) bench/sim_throughput.py

bench-augment: setup torch
	$(PYTHON) bench/augment_speed.py

bench-replay: setup torch
	$(PYTHON) bench/replay_stream.py

## bench-views: what named views and n-step returns cost beside RAD's crop batches (bench/views_cost.py)
bench-views: setup
	$(PYTHON) bench/views_cost.py

## bench-reverb: radserve's replay against DeepMind Reverb's on the same 84x84 frames (bench/vs_reverb.py);
## Reverb and its TensorFlow live in a venv of their own, .venv-reverb (bench/reverb-requirements.txt)
REVERB_VENV := .venv-reverb
$(REVERB_VENV)/.installed: bench/reverb-requirements.txt
	python3 -m venv $(REVERB_VENV)
	$(REVERB_VENV)/bin/python -m pip install -q -r bench/reverb-requirements.txt
	touch $@

bench-reverb: setup $(REVERB_VENV)/.installed
	$(PYTHON) bench/vs_reverb.py

## bench-learning: do the learners learn? SAC-state on InvertedPendulum, RAD-SAC vs pixel SAC on
## cartpole-balance, PPO on bigfish, DrQ-v2 on cartpole-swingup, prioritized DQN on CartPole; appends
## to docs/learning.md
bench-learning: setup torch
	$(PYTHON) bench/learning.py sac-state
	$(PYTHON) bench/learning.py rad-sac
	$(PYTHON) bench/learning.py ppo
	$(PYTHON) bench/learning.py drqv2
	$(PYTHON) bench/learning.py dqn-per

## docs-tables: render every benchmark table of the README and docs/ from bench/results/*.json, and
## docs/configuration.md's reference from the binary (tests/test_docs.py fails when they are stale)
docs-tables: build
	$(PYTHON) scripts/docs_tables.py --binary $(BIN)

## preview: docs/augment-preview.png, a grid of a dm_control frame under every augmentation
preview: setup
	$(BIN) augment-preview --env dmc/cartpole-balance --out docs/augment-preview.png

## lock: re-pin requirements.lock from requirements.in
lock: | $(PYTHON)
	$(PYTHON) -m pip install -q -r requirements.in
	$(PYTHON) -m pip freeze --exclude-editable | grep -vxF -f <(grep -hv '^#' requirements-envpool.lock requirements-k8s.lock) > requirements.lock

## api-snapshot: record new elements of the served gRPC API in proto/api-snapshot.txt (refused while
## an element was removed or changed: radserve.v1 only grows; server/radserve/tests/api_compat.rs)
api-snapshot: $(STAMP)
	RADSERVE_UPDATE_API_SNAPSHOT=1 cargo test --release -p radserve --test api_compat

## proto: regenerate the Python stubs (the Rust ones are generated by the service crate's build.rs)
proto: $(STAMP)
	client-py/scripts/gen_proto.sh

clean:
	cargo clean
	rm -rf $(VENV) dist
