"""Benchmarks: speed and memory (``python -m scripts.bench.all`` runs them together)."""
