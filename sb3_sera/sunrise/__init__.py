from sb3_sera.sunrise.buffers import SUNRISEDeviceReplayBuffer, SUNRISEReplayBuffer
from sb3_sera.sunrise.policies import MlpPolicy, SUNRISEPolicy
from sb3_sera.sunrise.sunrise import SUNRISE

__all__ = ["SUNRISE", "MlpPolicy", "SUNRISEDeviceReplayBuffer", "SUNRISEPolicy", "SUNRISEReplayBuffer"]
