# Two entry points: `make demo` and `make test`; both build the virtual environment first.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
DEMO_OUT ?= demo_out

.PHONY: demo test bench lint clean

$(BIN)/.installed: setup.cfg pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev,nerf,poses,collection,studio,splats]'
	touch $@

NERF := $(DEMO_OUT)/nerf
# About 13 minutes on 2 CPU cores: photos, then a simulated scene through a weight NeRF.
demo: $(BIN)/.installed
	$(BIN)/palette-decompose examples/photos -k 6 -o $(DEMO_OUT)/weights.npz --layers $(DEMO_OUT)/layers --force
	$(BIN)/python examples/edit_palette.py $(DEMO_OUT)/weights.palette.json -o $(DEMO_OUT)/edited_palette.json --force
	$(BIN)/palette-recolor $(DEMO_OUT)/weights.npz --palette $(DEMO_OUT)/edited_palette.json -o $(DEMO_OUT)/recolored --force
	$(BIN)/palette-harmonize $(DEMO_OUT)/weights.npz --template all -o $(DEMO_OUT)/harmonized/weights.npz --render $(DEMO_OUT)/harmonized --force
	$(BIN)/nerf-stage simulate still-life $(NERF)/still-life --force
	$(BIN)/palette-decompose $(NERF)/still-life/train -k 6 -o $(NERF)/weights.npz --force
	$(BIN)/palette-harmonize $(NERF)/weights.npz --template best -o $(NERF)/harmonized.npz --render $(NERF)/harmonized --force
	$(BIN)/nerf-stage train $(NERF)/still-life --weights $(NERF)/weights.npz -o $(NERF)/run --force
	$(BIN)/python examples/edit_palette.py $(NERF)/weights.palette.json -o $(NERF)/recolored.json --force
	$(BIN)/nerf-stage render $(NERF)/run --orbit 36 --palette $(NERF)/recolored.json --harmonize best -o $(NERF)/turntable --force
	$(BIN)/nerf-stage eval $(NERF)/run
	$(BIN)/nerf-stage bake $(NERF)/run --force
	$(BIN)/nerf-stage export $(NERF)/run --palette $(NERF)/recolored.json -o $(NERF)/recolored.ply --force
	@echo
	@echo "Demo outputs in $(DEMO_OUT)/:"
	@echo "  weights.palette.png, .json     extracted palette (swatch and JSON)"
	@echo "  weights.npz                    weight stack (format palette-weights/1)"
	@echo "  layers/                        one weight map per palette colour per photo"
	@echo "  edited_palette.json            the edited palette"
	@echo "  recolored/                     every photo recoloured with the edited palette"
	@echo "  harmonized/contact_sheet.png   the first photo harmonised by each of the seven templates"
	@echo "  harmonized/TEMPLATE/           every photo harmonised, hue_wheel.png, palette.png"
	@echo "  nerf/still-life/               the simulated scene (Blender format, 130 views)"
	@echo "  nerf/weights.npz, .palette.png its weights and palette from the training views"
	@echo "  nerf/harmonized/               the training views harmonised, hue wheel"
	@echo "  nerf/run/                      the weight NeRF (config.json, checkpoint.pt)"
	@echo "  nerf/turntable/recolored.gif   novel views recoloured with nerf/recolored.json"
	@echo "  nerf/turntable/harmonized-best.gif  novel views with the harmonised palette"
	@echo "  nerf/turntable/render.npz      the weight render; render again with another"
	@echo "                                 --palette to recolour it without the network"
	@echo "  nerf/run/splats.npz            the run baked into splats the browser draws"
	@echo "  nerf/recolored.ply             those splats recoloured, for 3D Gaussian splatting viewers"
	@echo
	@echo "Edit live in the browser: $(BIN)/palette-studio $(DEMO_OUT)/weights.npz"
	@echo "                      or: $(BIN)/palette-studio $(NERF)/run"

# Browser tests (palette-studio) need Debian's chromium and chromium-driver; without them they
# are skipped and the summary says so (-rs).
test: $(BIN)/.installed
	@command -v chromium >/dev/null && command -v chromedriver >/dev/null || \
		echo "chromium or chromedriver missing: the browser tests will be skipped"
	$(BIN)/python -m pytest -q -rs --durations=30

bench: $(BIN)/.installed
	$(BIN)/python benchmarks/bench_decompose.py
	$(BIN)/python benchmarks/bench_weights.py
	$(BIN)/python benchmarks/bench_simulate.py

lint: $(BIN)/.installed
	$(BIN)/ruff check .

clean:
	rm -rf $(VENV) $(DEMO_OUT) .pytest_cache .hypothesis
