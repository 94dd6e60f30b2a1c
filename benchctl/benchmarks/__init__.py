"""Benchmarks behind `benchctl bench ...`: each prints a table of times measured side by side with errors."""
