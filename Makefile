# mi-neurallens — two commands for a fresh machine (see README.md):
#   make demo   set up, then run the main job on bundled defaults (side-by-side render in out/demo/)
#   make test   set up, then run the default test suite (about 5 min on 2 cores); `make test-slow` for the long ones
PY ?= python3
OUT ?= out

.PHONY: setup demo test test-slow bench docs

setup:
	@bash scripts/setup.sh

# The main job on bundled defaults: the 22 mm lens, its layout, and the still life rendered with the
# exact tracer (converged reference + equal-spp) and with the neural map, side by side with MAPE.
demo: setup
	$(PY) -m mi_neurallens demo --out $(OUT)/demo

test: setup
	$(PY) -m pytest -q -ra

test-slow: setup
	$(PY) -m pytest -q -ra -m slow

# The maintained benchmarks, each writing its JSON into $(OUT)/bench/ (docs/performance.md says which figure
# comes from which); `python docs/make_performance.py --from $(OUT)/bench` then takes the new figures.
bench: setup
	$(PY) benchmarks/bench_tracer.py --out $(OUT)/bench/bench_tracer.json
	$(PY) benchmarks/bench_mlp.py --out $(OUT)/bench/bench_mlp.json
	$(PY) benchmarks/bench_render.py --out $(OUT)/bench/bench_render.json
	$(PY) benchmarks/bench_flare.py --out $(OUT)/bench/bench_flare.json
	$(PY) benchmarks/equal_time.py --out $(OUT)/bench/equal_time.json
	$(PY) benchmarks/bench_baselines.py --out $(OUT)/bench/bench_baselines.json

# The generated parts of the docs (figure tables, plugin parameters, lists of bundled lenses and models).
docs: setup
	$(PY) docs/make_performance.py
	$(PY) docs/make_reference.py
