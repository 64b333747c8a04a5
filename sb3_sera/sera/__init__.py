from sb3_sera.sera.policies import CnnPolicy, MlpPolicy, MultiInputPolicy
from sb3_sera.sera.sera import SERASAC

__all__ = ["SERASAC", "CnnPolicy", "MlpPolicy", "MultiInputPolicy"]
