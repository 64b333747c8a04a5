from sb3_sera.sunrise.buffers import SUNRISEReplayBuffer
from sb3_sera.sunrise.policies import MlpPolicy, SUNRISEPolicy
from sb3_sera.sunrise.sunrise import SUNRISE

__all__ = ["SUNRISE", "MlpPolicy", "SUNRISEPolicy", "SUNRISEReplayBuffer"]
