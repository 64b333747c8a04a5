"""Experiment tooling: comparisons, command line."""
