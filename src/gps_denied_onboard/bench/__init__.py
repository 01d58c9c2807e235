"""Benchmarks that print measured figures (``gdnav bench ...``)."""
