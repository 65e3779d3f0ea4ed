# Two entry points: `make demo` and `make test`; both build the virtual environment first.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
DEMO_OUT ?= demo_out

.PHONY: demo test bench lint clean

$(BIN)/.installed: setup.cfg pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev,nerf]'
	touch $@

demo: $(BIN)/.installed
	$(BIN)/palette-decompose examples/photos -k 6 -o $(DEMO_OUT)/weights.npz --layers $(DEMO_OUT)/layers --force
	$(BIN)/python examples/edit_palette.py $(DEMO_OUT)/palette.json -o $(DEMO_OUT)/edited_palette.json --force
	$(BIN)/palette-recolor $(DEMO_OUT)/weights.npz --palette $(DEMO_OUT)/edited_palette.json -o $(DEMO_OUT)/recolored --force
	$(BIN)/palette-harmonize $(DEMO_OUT)/weights.npz --template all -o $(DEMO_OUT)/harmonized/weights.npz --render $(DEMO_OUT)/harmonized --force
	@echo
	@echo "Demo outputs in $(DEMO_OUT)/:"
	@echo "  palette.png, palette.json      extracted palette (swatch and JSON)"
	@echo "  weights.npz                    weight stack (format palette-weights/1)"
	@echo "  layers/                        one weight map per palette colour per photo"
	@echo "  edited_palette.json            the edited palette"
	@echo "  recolored/                     every photo recoloured with the edited palette"
	@echo "  harmonized/contact_sheet.png   the first photo harmonised by each of the seven templates"
	@echo "  harmonized/TEMPLATE/           every photo harmonised, hue_wheel.png, palette.png"

test: $(BIN)/.installed
	$(BIN)/python -m pytest -q

bench: $(BIN)/.installed
	$(BIN)/python benchmarks/bench_decompose.py
	$(BIN)/python benchmarks/bench_weights.py
	$(BIN)/python benchmarks/bench_simulate.py

lint: $(BIN)/.installed
	$(BIN)/ruff check .

clean:
	rm -rf $(VENV) $(DEMO_OUT) .pytest_cache .hypothesis
