"""Benchmarks: fields, registration, rendering, encodings and distillation, each a function that
writes JSON rows, run by ``regnf bench ...`` (:mod:`regnf.benchmarks.cli`). The tables are in
docs/benchmarks.md.
"""
