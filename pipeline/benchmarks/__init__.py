"""Benchmark scripts: each prints its numbers beside a plain baseline measured in the same run.

Run as ``python -m pipeline.benchmarks.<name> --help``.  Never imported by the pipeline itself.
"""
