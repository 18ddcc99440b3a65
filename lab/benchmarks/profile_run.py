"""Run a Python module under cProfile and keep the profile even when the run is stopped.

    python benchmarks/profile_run.py OUT.pstats -m MODULE [ARGS...]

``timeout`` (and the device tool's deadline) end a run with SIGTERM, which would lose what ``python -m
cProfile`` collected: here SIGTERM (and SIGINT) write ``OUT.pstats`` before the process exits, with status 124
as ``timeout`` reports it.  ``benchmarks/gpu_suite.sh`` uses it for ``GPU_SUITE_PROFILE=1``: where a whole-lens
training spends its set-up on a GPU (host numpy, the CUDA driver's compilation, the tracer) is what a timed run
cannot say.  Read the result with ``python -c "import pstats; pstats.Stats('OUT.pstats').sort_stats('cumulative')
.print_stats(40)"``.
"""
from __future__ import annotations

import cProfile
import os
import runpy
import signal
import sys


def main(argv: list[str]) -> int:
    if len(argv) < 3 or argv[1] != "-m":
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    out, module, args = argv[0], argv[2], argv[3:]
    prof = cProfile.Profile()
    written = []

    def write(*_):
        if not written:
            prof.disable()
            prof.dump_stats(out)
            written.append(out)
            print(f"profile_run: wrote {out}", file=sys.stderr, flush=True)

    def stop(signum, _frame):
        write()
        os._exit(124)                      # what `timeout` reports; skip the interrupted program's clean-up

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    sys.argv = [module] + args
    prof.enable()
    try:
        runpy.run_module(module, run_name="__main__", alter_sys=True)
    except SystemExit as e:
        return e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    finally:
        write()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
