# mi-neurallens — two commands for a fresh machine (see README.md):
#   make demo   set up, then run the main job on bundled defaults (side-by-side render in out/demo/)
#   make test   set up, then run the default test suite (< 10 min); `make test-slow` for the long ones
PY ?= python3
OUT ?= out

.PHONY: setup demo test test-slow bench

setup:
	@bash scripts/setup.sh

# The main job on bundled defaults: the 22 mm lens, its layout, and the still life rendered with the
# exact tracer (converged reference + equal-spp) and with the neural map, side by side with MAPE.
demo: setup
	$(PY) -m mi_neurallens lens info wide-22mm
	$(PY) -m mi_neurallens lens plot wide-22mm -o $(OUT)/wide-22mm-layout.png
	$(PY) -m mi_neurallens compare scenes/still_life.xml --spp 64 --reference-spp 1024 --out $(OUT)/demo
	@echo "side by side: $(OUT)/demo/compare.png (table: $(OUT)/demo/compare.md)"

test: setup
	$(PY) -m pytest -q -ra

test-slow: setup
	$(PY) -m pytest -q -ra -m slow

bench: setup
	$(PY) benchmarks/bench_tracer.py
	$(PY) benchmarks/bench_mlp.py
	$(PY) benchmarks/bench_render.py
