"""Declarative joint-error model files, one per variant; discovered by bayesrob.noise_models."""
