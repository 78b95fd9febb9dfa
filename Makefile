# Two commands set everything up on a fresh machine: `make demo` and `make test`.
# Each creates .venv when missing and installs what is needed (a no-op when up to date).

PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DEMO_DATA := data/demo
DEMO_RUN := outputs/demo/gaussian-atoms/demo

.PHONY: install demo test format clean

install: $(STAMP)

$(STAMP): pyproject.toml setup.py constraints.txt gaussian_atoms_method/launch/gaussian_atoms_quiet.pth
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	PYTHONWARNINGS=ignore $(BIN)/python -m pip install --quiet -c constraints.txt -e ".[test,sim]"
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/gaussian-atoms simulate --output $(DEMO_DATA) --particle sphere --element Au --radius-A 11 \
		--potential gaussian --tilts limited --noise-std 20
	rm -rf outputs/demo
	$(BIN)/ns-train gaussian-atoms --machine.device-type cpu --vis tensorboard \
		--output-dir outputs --experiment-name demo --timestamp demo \
		tilt-series --data $(DEMO_DATA)
	$(BIN)/gaussian-atoms evaluate --pred $(DEMO_RUN)/atoms.xyz --truth $(DEMO_DATA)/atoms_true.xyz

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	OMP_NUM_THREADS=1 $(BIN)/python -m pytest -q -n auto --maxprocesses 4 --durations=25 --doctest-modules tests gaussian_atoms_method dataparsers

format: $(STAMP)
	$(BIN)/ruff format .
	$(BIN)/ruff check --fix .

clean:
	rm -rf outputs $(DEMO_DATA)
