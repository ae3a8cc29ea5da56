"""Benchmark suites: ``terrain-bench SUITE`` runs ``terrain_perception/bench/SUITE.py``."""
