"""
Why a saved model does not load into an algorithm of the package, in one line: a file of another algorithm (SB3's
own error is a ``KeyError`` of an optimizer's name), or one saved with other networks than the model it is loaded
into (torch's lists every missing weight).
"""

from pathlib import Path
from typing import Any

from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.save_util import load_from_zip_file


def _saved_data(path: str | Path | Any) -> dict[str, Any] | None:
    """The saved model's data (its class arguments, policy class and ``policy_kwargs``), None where it cannot be read."""
    try:
        data, _, _ = load_from_zip_file(path, load_data=True, device="cpu")
    except (OSError, ValueError, KeyError, RuntimeError):
        return None
    return data


def _qualified(policy_class: type) -> str:
    return f"{policy_class.__module__}.{policy_class.__qualname__}"


def foreign_file_reason(algorithm: type[BaseAlgorithm], path: str | Path | Any) -> str | None:
    """
    Why ``path`` is no file of ``algorithm``: its policy is none of ``algorithm``'s (a model of another algorithm);
    None where it is one of them, or the file cannot be read.
    """
    data = _saved_data(path)
    policy_class = None if data is None else data.get("policy_class")
    ours = tuple(policy for policy in algorithm.policy_aliases.values() if isinstance(policy, type))
    if not isinstance(policy_class, type) or not ours or issubclass(policy_class, ours):
        return None
    return (
        f"{path} holds a model of another algorithm: its policy is {_qualified(policy_class)}, where "
        f"{algorithm.__name__}'s are {', '.join(sorted({policy.__name__ for policy in ours}))}; load it with the "
        "algorithm that saved it"
    )


def other_networks_reason(model: BaseAlgorithm, path: str | Path | Any) -> str | None:
    """
    Why the weights of ``path`` do not fit ``model``: the file's model was built with other ``policy_kwargs`` (another
    ensemble size, other layers) or is of another algorithm; None where neither can be told.
    """
    foreign = foreign_file_reason(type(model), path)
    data = _saved_data(path)
    if foreign is not None or data is None:
        return foreign
    saved = {key: value for key, value in (data.get("policy_kwargs") or {}).items() if key != "use_sde"}
    asked = {key: value for key, value in (model.policy_kwargs or {}).items() if key != "use_sde"}
    return (
        f"{path} holds a {type(model).__name__} built with policy_kwargs={saved}, where this model has "
        f"policy_kwargs={asked}{' (the defaults)' if not asked else ''}: their networks differ. Build the model with "
        f"the file's policy_kwargs, or load the file with {type(model).__name__}.load(path), which builds its networks"
    )
