"""Benchmarks run as ``virgi-bench`` subcommands."""
