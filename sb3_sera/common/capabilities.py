"""What an algorithm of the package supports, declared on its class (BenchMARL's way) instead of lists kept elsewhere."""

from typing import Any, ClassVar

from sb3_sera.common.tuning import TuningSpace


class Capabilities:
    """
    Class attributes every algorithm of the package sets: the zoo bridge, the run engine and the playback commands
    read them, so that adding an algorithm means declaring them on its class.
    """

    #: Trains on single-agent Gymnasium tasks
    single_agent: ClassVar[bool] = True
    #: Trains on the multi-agent CTDE tasks (``"CTDEPolicy"``)
    multi_agent: ClassVar[bool] = True
    #: Learns from a replay buffer (rl-zoo3's playback loads such a model with a one-transition buffer)
    off_policy: ClassVar[bool] = True
    #: Has Q critics ``critic(obs, action)`` (the evaluations record the initial-state bias and critic diagnostics)
    has_q_critics: ClassVar[bool] = True
    #: The SB3 algorithm (rl-zoo3's name) whose hyperparameter sampler tunes it; None: a sampler of its own
    tunes_like: ClassVar[str | None] = None
    #: Its own search space for rl-zoo3's ``optimize`` (:class:`~sb3_sera.common.tuning.TuningSpace`), declared
    #: beside the algorithm; None: it tunes like ``tunes_like``
    tuning: ClassVar[TuningSpace | None] = None


def capabilities(algorithm: type[Any]) -> dict[str, Any]:
    """The capabilities an algorithm class declares (every attribute of :class:`Capabilities`)."""
    names = [name for name in vars(Capabilities) if not name.startswith("_")]
    return {name: getattr(algorithm, name) for name in names}
