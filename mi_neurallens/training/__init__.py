"""Training the learned maps (torch is imported lazily, inside the functions).

* the data: ``data.py`` (the training streams, drawn through the exact map's sampler in
  :mod:`mi_neurallens.transport.sampling` and :mod:`~mi_neurallens.transport.bounds`; planes and domains in
  :mod:`mi_neurallens.transport.planes`), ``config.py`` (recipes and their defaults);
* one network: ``nets.py`` (torch helpers), ``outputs.py`` (output standardisation, loss weights),
  ``regressor.py``, ``classifier.py``, ``stop_head.py`` (each network's problem and its training),
  ``input_box.py``;
* many networks at once: ``stacked.py`` (Adam on a stack), ``fused_cpu.py`` + ``fused_mlp.c`` (a CPU step in one
  kernel), ``levenberg.py`` (the Levenberg–Marquardt finish and the driver that finishes a run's networks);
* maps: ``maps.py`` (the maps of one direction, the architecture ladder), ``keep.py`` (what a run takes from a
  base model), ``whole_lens.py`` (``mi-neurallens train``: a whole lens), ``distributed.py`` and ``merge.py``
  (a catalogue on Ray, merged), ``evaluate.py`` (held-out metrics).
"""
