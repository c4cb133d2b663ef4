"""The methods (layer 4): the table of methods, the interface every method keeps, and the registry.

- :mod:`~neural_estimator.methods.table`: one frozen ``MethodSpec`` per method (names, family,
  capabilities, its factory as ``"module:attribute"`` text); every question about methods is a query
  of it;
- :mod:`~neural_estimator.methods.interface`: ``Estimator``, ``Estimates``, ``EstimatorError``,
  ``check_method``;
- :mod:`~neural_estimator.methods.registry`: ``make_estimator``, which builds a method of the table by
  resolving its factory with importlib then, so nothing here imports the filters, models or serving
  above.
"""
