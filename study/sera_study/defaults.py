"""
The defaults the ``sb3-sera`` command line shows in its help, in a module that imports nothing: ``--help`` and an
argument's error are answered before torch and Stable-Baselines3 are imported. The modules that use them import
them from here.
"""

#: Default quick comparison: a task that SAC solves in a few thousand steps
DEFAULT_ENV = "Pendulum-v1"
DEFAULT_ALGOS = ("serasac", "sac")
DEFAULT_SEEDS = (0, 1)
DEFAULT_TIMESTEPS = 6_000
#: Bootstrap replications by default
REPS = 5000
#: Steps between checkpoints by default: a 50K-step run keeps at most 10K steps of work at risk
CHECKPOINT_FREQ = 10_000
#: The ledger's folder, at the top of the repository
LEDGER_DIR = "results"
#: Where the full report from the ledger goes
DOCS_DIR = "docs/results"
#: Bootstrap resamples of the README's and docs' intervals
LEDGER_REPS = 2000
#: The zoo commands the CLI passes through
ZOO_COMMANDS = ("train", "enjoy", "record-video", "optimize")
