# Two commands do all set-up on a fresh machine with python3 and make:
#   make demo   runs the main job on the embedded default sample
#   make test   runs the test suite
# Both install into .venv with the tested versions (constraints.txt); `make demo` installs
# only the extras the demo runs, `make test` the dev extra (everything plus the test tools).
# Each has its own stamp, so one .venv serves both; a changed pyproject.toml or
# constraints.txt reinstalls.
PYTHON      ?= python3
VENV        := .venv
PY          := $(VENV)/bin/python
PIP         := $(PY) -m pip install --quiet -c constraints.txt
DEMO_STAMP  := $(VENV)/.installed-demo
DEV_STAMP   := $(VENV)/.installed-dev
# the process demo: the edge services, the ledger and projector services, the simulator
DEMO_EXTRAS := edge,ledger,projector,sim

.PHONY: demo test accuracy bench schemas clean mutate faults

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

$(DEMO_STAMP): pyproject.toml constraints.txt | $(PY)
	$(PIP) -e '.[$(DEMO_EXTRAS)]'
	@touch $@

$(DEV_STAMP): pyproject.toml constraints.txt | $(PY)
	$(PIP) -e '.[dev]'
	@touch $@

demo: $(DEMO_STAMP)
	$(VENV)/bin/stockpile demo

test: $(DEV_STAMP)
	$(VENV)/bin/lint-imports --no-cache
	$(PY) -m pytest -q

# The quick accuracy check alone (make test runs it too): the analytic piles of
# bench/accuracy.py and the demo seed of bench/projector_truth.py against their targets.
accuracy: $(DEV_STAMP)
	$(PY) -m pytest -q -m accuracy

# Every fault-injection case (tests/faults), the long ones and the 30-minute soak included
# (STOCKPILE_SOAK_MINUTES=3 make faults tries it short); make test runs only the quick ones.
# Ends with the table of the cases' rows (build/faults/results.jsonl), pass or fail.
faults: $(DEV_STAMP)
	rm -f build/faults/results.jsonl
	$(PY) -m pytest -q -p no:cacheprovider tests/faults --long-faults; \
	status=$$?; $(PY) tests/faults/table.py build/faults/results.jsonl; exit $$status

bench: $(DEV_STAMP)
	$(PY) bench/ledger.py

# Mutation testing of the core (tools/mutate.py, docs/mutation.md): a table per module,
# every survivor with its reason; fails below 90 % or on an unexplained survivor.
mutate: $(DEV_STAMP)
	$(PY) tools/mutate.py

# Regenerate schemas/stockpile/v1/*_pb2.py from schemas/proto (commit the result).
schemas: $(DEV_STAMP)
	$(PY) -m schemas.generate

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache demo-out
