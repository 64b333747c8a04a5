"""
The SERA study of sb3-sera: the ``sb3-sera`` command line, comparisons and benchmarks through one run engine, the
results ledger with its declared claims, statistics, reports and figures, and the theory study of target estimators.
"""

__version__ = "0.1.0"
