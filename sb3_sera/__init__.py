"""sb3-sera: Soft Ensemble Reliability Aggregation (SERA) for Stable-Baselines3."""

from sb3_sera.sera import SERASAC

__version__ = "0.1.0"

__all__ = ["SERASAC", "__version__"]
