from sb3_sera.ace.ace import ACE
from sb3_sera.ace.policies import ACEPolicy, MlpPolicy

__all__ = ["ACE", "ACEPolicy", "MlpPolicy"]
