# mi-neurallens — two commands for a fresh machine (see README.md):
#   make demo   set up, then run the main job on bundled defaults
#   make test   set up, then run the default test suite (< 10 min); `make test-slow` for the long ones
PY ?= python3
OUT ?= out

.PHONY: setup demo test test-slow bench

setup:
	@bash scripts/setup.sh

demo: setup
	$(PY) -m mi_neurallens lens info wide-22mm
	$(PY) -m mi_neurallens lens plot wide-22mm -o $(OUT)/wide-22mm-layout.png
	@echo "wrote $(OUT)/wide-22mm-layout.png"

test: setup
	$(PY) -m pytest -q -ra

test-slow: setup
	$(PY) -m pytest -q -ra -m slow

bench: setup
	$(PY) benchmarks/bench_tracer.py
