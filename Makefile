# mi-neurallens — two commands for a fresh machine (see README.md):
#   make demo   set up, then run the main job on bundled defaults (side-by-side render in out/demo/)
#   make test   set up, then run the default test suite (about 5.5 min on 2 cores, two pytest-xdist workers); `make test-slow` for the long ones
PY ?= python3
OUT ?= out

.PHONY: setup demo test test-slow bench docs

setup:
	@bash scripts/setup.sh

# The main job on bundled defaults: the 22 mm lens, its layout, and the still life rendered with the
# exact tracer (converged reference + equal-spp) and with the neural map, side by side with MAPE.
demo: setup
	$(PY) -m mi_neurallens demo --out $(OUT)/demo

# Two workers (pytest-xdist), a test file each at a time: most tests wait on one thread (LLVM compiling a kernel,
# Python), so two of them keep both cores busy (with cheaper training tests: 8.7 -> 5.4 min on 2 cores).
test: setup
	$(PY) -m pytest -q -ra -n 2 --dist loadfile

test-slow: setup
	$(PY) -m pytest -q -ra -m slow

# The maintained benchmarks, each writing its JSON into $(OUT)/bench/ (docs/performance.md says which figure
# comes from which); `python docs/make_performance.py --from $(OUT)/bench` then takes the new figures. About 21 min
# on 2 cores; run it on an idle machine.
BENCH_LENSES ?= wide-22mm ood-59mm canon-ef-24mm-f1.4l canon-rf-24mm-f1.4l-vcm canon-ef-24-70mm-f2.8l
bench: setup
	$(PY) benchmarks/bench_tracer.py --out $(OUT)/bench/bench_tracer.json
	for lens in $(BENCH_LENSES); do \
	    $(PY) benchmarks/bench_mlp.py --lens $$lens --out $(OUT)/bench/mlp_$$lens.json || exit 1; \
	    $(PY) benchmarks/bench_render.py --lens $$lens --out $(OUT)/bench/render_$$lens.json || exit 1; \
	done
	$(PY) benchmarks/bench_flare.py --out $(OUT)/bench/bench_flare.json
	for lens in wide-22mm ood-59mm; do \
	    $(PY) benchmarks/bench_flare.py --starburst --lens $$lens --out $(OUT)/bench/starburst_$$lens.json || exit 1; \
	done
	$(PY) benchmarks/bench_flare.py --lens ood-59mm --coatings none,quarter_wave,broadband --out $(OUT)/bench/coatings_ood-59mm.json
	$(PY) benchmarks/bench_flare.py --lens ood-59mm --coatings none,quarter_wave,broadband --scene night --out $(OUT)/bench/coatings_night_ood-59mm.json
	$(PY) benchmarks/equal_time.py --out $(OUT)/bench/equal_time.json
	$(PY) benchmarks/bench_zoom.py --out $(OUT)/bench/bench_zoom.json
	$(PY) benchmarks/bench_zoom.py --focal 24.9,35,68.14 --focus inf --res 640x424 --reference-spp 64 --repeats 4 --out $(OUT)/bench/bench_zoom_640.json
	$(PY) benchmarks/bench_zoom.py --lens canon-rf-24mm-f1.4l-vcm --focal none --focus inf,2,1,0.5,0.3,0.24 --out $(OUT)/bench/bench_focus.json
	$(PY) benchmarks/bench_baselines.py --out $(OUT)/bench/bench_baselines.json
	$(PY) -m mi_neurallens accuracy wide-22mm --out $(OUT)/bench

# The generated parts of the docs (figure tables, plugin parameters, lists of bundled lenses and models).
docs: setup
	$(PY) docs/make_performance.py
	$(PY) docs/make_reference.py
