"""
The room that reads run folders: runs grouped by their settings (:mod:`~sera_study.results.groups`), the statistics,
the per-run measures, the declared claims and how they are decided, the ledger and its intake, and the report. It
reads the run-folder contract (:mod:`sera_study.records`) and imports nothing of :mod:`sera_study.runs`.
"""
