"""Benchmarks and studies, run as ``python -m benchmarks.<name>``: outside the library, each smoke-tested."""
