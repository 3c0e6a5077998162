# The README's commands. Every target does its own setup: a .venv with the
# local CPU torch build installed first, then the project with its test and
# bench extras; `make test` also installs Chromium for the browser tests.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-$(shell cksum pyproject.toml | cut -d' ' -f1)
# the browser tests drive Debian's chromium; apt-get needs root (sudo when not root)
SUDO   := $(if $(filter 0,$(shell id -u)),,sudo)

.PHONY: setup browser test demo bench lint clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --upgrade pip
	$(PY) -m pip install torch==2.13.0
	$(PY) -m pip install -e '.[test,bench]'
	rm -f $(VENV)/.installed-*
	touch $@

browser:
	command -v chromium >/dev/null || { $(SUDO) apt-get update && \
		$(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y chromium; }

test: $(STAMP) browser
	$(VENV)/bin/ruff check shared services tests
	$(VENV)/bin/mypy
	$(PY) -m pytest -q

demo: $(STAMP)
	$(VENV)/bin/aesop demo

bench: $(STAMP)
	$(VENV)/bin/aesop bench detector

lint: $(STAMP)
	$(VENV)/bin/ruff check shared services tests
	$(VENV)/bin/mypy

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
