"""Benchmarks: run `python -m benchmarks` for all, or `python -m benchmarks.bench_NAME`."""
