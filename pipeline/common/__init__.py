"""Shared plumbing of every stage: atomic writes, column schemas, strict CSV and YAML, RMSE.

Imports nothing else of :mod:`pipeline` (docs/architecture.md).
"""
