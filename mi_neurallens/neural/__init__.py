"""Neural lens transport maps: the model file (:mod:`.model`) and MLP evaluation (:mod:`.mlp`).

What a renderer calls::

    from mi_neurallens.neural import NeuralLensModel
    model = NeuralLensModel.load(path, lens=lens)      # ModelError on any problem
    tm = model.map("transmit", "backward")              # a NeuralMap; or model.map(ghost_id, "forward")
    res = tm.eval_dr(o, d, lam)                         # a MapResult: Dr.Jit, lens space, fused literals

Nothing here imports torch.
"""
from .model import FORMAT, FORMAT_VERSION, NeuralLensModel, NeuralMap, bundled_model_path, load_model

__all__ = ["NeuralLensModel", "NeuralMap", "load_model", "bundled_model_path", "FORMAT", "FORMAT_VERSION"]
