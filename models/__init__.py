"""Declarative joint-error model files, one per variant; read by bayesrob.errors.noise_models."""
