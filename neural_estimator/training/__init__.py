"""Training a neural estimator with the paper's protocol.

- :mod:`~neural_estimator.training.recipe`: :class:`TrainConfig`, the recipe (free of torch);
- :mod:`~neural_estimator.training.loop`: :func:`train`, the run, and :func:`evaluate`, the final measure;
- :mod:`~neural_estimator.training.loss`: the weighted loss of a batch of windows;
- :mod:`~neural_estimator.training.stopping`: the convergence and plateau rules;
- :mod:`~neural_estimator.training.resume`: the resume state, bit-for-bit.

This package's ``__init__`` imports nothing, so reading the recipe does not import torch.
"""
