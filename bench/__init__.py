"""Benchmarks run by `make bench` (each bench_*.py module exposes bench_* functions)."""
