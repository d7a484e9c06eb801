"""Runners, evaluation, the report, benchmarks and the command line: what
builds a diagram and runs it. The top layer."""
