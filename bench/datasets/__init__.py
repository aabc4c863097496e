"""Readers of the benchmark data under ``../shared/data``, and synthetic problems built from it."""
