from sb3_sera.sera.policies import CnnPolicy, MlpPolicy, MultiInputPolicy
from sb3_sera.sera.sera import PAPER_RATES, SERASAC

__all__ = ["PAPER_RATES", "SERASAC", "CnnPolicy", "MlpPolicy", "MultiInputPolicy"]
