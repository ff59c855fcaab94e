"""Fitting a model from a config (the library side of ``python -m matl.train``)."""
