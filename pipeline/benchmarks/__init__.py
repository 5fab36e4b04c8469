"""Benchmarks behind the `relight bench-*` commands: timings reported, never asserted."""
