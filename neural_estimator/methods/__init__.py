"""The methods: the interface every estimator keeps (:mod:`neural_estimator.methods.interface`)."""
