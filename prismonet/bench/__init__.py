"""Benchmarks, run as commands (``prismonet bench ...``), never as timed tests."""
