# Two commands do all set-up on a fresh machine with python3 and make:
#   make demo   runs the main job on the embedded default sample
#   make test   runs the test suite
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test bench schemas clean

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	@touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/stockpile demo

test: $(STAMP)
	$(VENV)/bin/lint-imports --no-cache
	$(PY) -m pytest -q

bench: $(STAMP)
	$(PY) bench/ledger.py

# Regenerate schemas/stockpile/v1/*_pb2.py from schemas/proto (commit the result).
schemas: $(STAMP)
	$(PY) -m schemas.generate

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache demo-out
