"""Serving a trained neural model as an estimator.

- :mod:`~neural_estimator.serving.card`: the checkpoint's files and its card (JSON helpers, digests);
- :mod:`~neural_estimator.serving.checkpoint`: writing and loading a checkpoint (safetensors + card);
- :mod:`~neural_estimator.serving.normalization`: the normalisation statistics a model was trained with;
- :mod:`~neural_estimator.serving.context`: the bounded context (restarted copies of a model);
- :mod:`~neural_estimator.serving.neural`: :class:`NeuralEstimator`, a model behind the estimator contract;
- :mod:`~neural_estimator.serving.load`: the shipped zoo, the scenario check, the estimator a
  checkpoint makes;
- :mod:`~neural_estimator.serving.onnx_runtime`: a model's exported step on ONNX Runtime, without torch;
- :mod:`~neural_estimator.serving.export`: writing that step (``step.onnx``) beside a checkpoint's card.

The architectures themselves are in :mod:`neural_estimator.models`; training in
:mod:`neural_estimator.training`.
"""
