from sb3_sera.iet.iet import IET
from sb3_sera.iet.policies import IETPolicy

__all__ = ["IET", "IETPolicy"]
