"""
A model's training mode set in one pass over a list of its modules: SB3 sets it before every action and every
``train()``, and ``Module.train`` walks the module tree each time (``docs/speed.md``, "The host floor").
"""

import weakref
from typing import Any

from torch import nn
from torch.nn.modules.module import register_module_module_registration_hook

#: Submodules registered on any module of the process so far: a flag list made before a registration may be stale
_registrations = 0
_counting = False

#: Each module's flag list: the registrations it was made after, the modules whose ``training`` flag is set directly
#: (their classes keep ``nn.Module.train``) and those whose own ``train`` is called (it sets their submodules)
_plans: "weakref.WeakKeyDictionary[nn.Module, tuple[int, list[nn.Module], list[nn.Module]]]" = weakref.WeakKeyDictionary()


def _count_registration(module: nn.Module, name: str, submodule: nn.Module | None) -> None:
    global _registrations
    _registrations += 1


def set_training_flags(module: nn.Module, mode: bool) -> None:
    """
    ``module.train(mode)``: the ``training`` flag of each module of the tree whose class keeps ``nn.Module.train`` set
    directly, without ``nn.Module.__setattr__``, and a module whose class overrides ``train`` given its own
    ``train(mode)`` call (which sets its submodules). The tree's list is made at the first call and again after any
    submodule is registered anywhere (a process-wide count, one ``torch.nn`` registration hook).

    :param mode: if true, set to training mode, else set to evaluation mode
    """
    global _counting
    if not isinstance(mode, bool):
        raise ValueError(f"training mode is expected to be boolean, got {mode!r}")
    if not _counting:
        register_module_module_registration_hook(_count_registration)
        _counting = True
    plan = _plans.get(module)
    if plan is None or plan[0] != _registrations:
        plan = (_registrations, *_flag_lists(module))
        _plans[module] = plan
    for current in plan[1]:
        current.__dict__["training"] = mode
    for current in plan[2]:
        current.train(mode)


def _flag_lists(module: nn.Module) -> tuple[list[nn.Module], list[nn.Module]]:
    direct, own = [], []
    stack = [module]
    while stack:
        current = stack.pop()
        if type(current).train is not nn.Module.train:
            own.append(current)
            continue
        direct.append(current)
        stack.extend(child for child in current._modules.values() if child is not None)
    return direct, own


class ActorCriticTrainingMode:
    """
    A policy's ``set_training_mode`` as SB3's SAC and TD3 policies have it (the actor and the critics in training or
    evaluation mode, not the target critics), each set in one pass (:func:`set_training_flags`). Comes before the SB3
    policy in the bases.
    """

    # Any: each SB3 policy declares its own actor and critic classes
    actor: Any
    critic: Any
    training: bool

    def set_training_mode(self, mode: bool) -> None:
        """
        Put the actor and the critics in training or evaluation mode.

        :param mode: if true, set to training mode, else set to evaluation mode
        """
        set_training_flags(self.actor, mode)
        set_training_flags(self.critic, mode)
        self.training = mode
