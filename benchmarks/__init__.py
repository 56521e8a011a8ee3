"""Benchmarks: every speed claim of the project, measured side by side. See benchmarks/README.md."""
