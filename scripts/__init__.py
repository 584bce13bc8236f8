"""Runnable scripts, never imported by the packages: ``bench/`` (speed and memory), ``eval/`` (measurements
and experiments), ``tools/`` (builds, drills, checks). Run one from the repository's root as a module, e.g.
``.venv/bin/python -m scripts.bench.dub --help``; what they share is :mod:`scripts.common`."""
