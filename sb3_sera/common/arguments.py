"""
What every algorithm checks of its constructor's arguments before SB3 sees them: the keywords' names and the env.

- An unknown keyword (a typo, or one of the policy's arguments given to the algorithm) raises ``TypeError`` naming it,
  its close matches and every keyword the algorithm takes, or saying that it belongs in ``policy_kwargs``
  (:func:`check_keywords`; :func:`checks_keywords` does it for a constructor with an explicit signature, which it keeps),
  and so does a keyword of ``policy_kwargs`` that the policy does not take (:func:`check_policy_keywords`).
- A PettingZoo env, which SB3 would take for an old Gym env, raises ``TypeError`` saying how to wrap it
  (:func:`check_gymnasium_env`).

Neither changes an argument: what they accept builds the model it built before.
"""

import difflib
import functools
import inspect
from collections.abc import Callable, Iterable, Mapping
from typing import Any, TypeVar, cast

from pettingzoo.utils.env import AECEnv, ParallelEnv

#: How many close matches of an unknown keyword its message suggests
N_CLOSE_MATCHES = 3
#: The policy's arguments that the algorithm fills itself, never given in ``policy_kwargs``
_ALGORITHM_FILLED = ("observation_space", "action_space", "lr_schedule")
#: Longest value written out in a ``policy_kwargs=dict(...)`` suggestion
_MAX_VALUE_LENGTH = 40

_NAMED = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)

InitT = TypeVar("InitT", bound=Callable[..., None])


def keyword_names(signature: inspect.Signature) -> list[str] | None:
    """The names ``signature`` takes as keywords, in order; None when it takes any (``**kwargs``)."""
    parameters = signature.parameters.values()
    if any(parameter.kind is inspect.Parameter.VAR_KEYWORD for parameter in parameters):
        return None
    return [parameter.name for parameter in parameters if parameter.kind in _NAMED]


def _policy_keywords(policy_class: type) -> tuple[list[str], bool]:
    """
    The keywords a policy class takes in ``policy_kwargs``: its constructor's, and, while a constructor passes
    ``**kwargs`` on, those of the next constructor in its bases; and whether that chain ends (a constructor without
    ``**kwargs``), so that the names are all it takes.
    """
    names: list[str] = []
    for base in policy_class.__mro__:
        init = base.__dict__.get("__init__")
        if init is None:
            continue
        parameters = list(inspect.signature(init).parameters.values())[1:]  # after self
        names += [p.name for p in parameters if p.kind in _NAMED and p.name not in names + list(_ALGORITHM_FILLED)]
        if not any(parameter.kind is inspect.Parameter.VAR_KEYWORD for parameter in parameters):
            return names, True
    return names, False


def policy_keyword_names(policy_class: type) -> list[str]:
    """
    The keywords a policy class takes in ``policy_kwargs``: its constructor's, and, while a constructor passes
    ``**kwargs`` on, those of the next constructor in its bases (SERA's ``CnnPolicy`` passes them to ``SERAPolicy``).
    """
    return _policy_keywords(policy_class)[0]


def check_policy_keywords(algorithm: type, policy: Any, policy_kwargs: Any) -> None:
    """
    Raise ``TypeError`` if ``policy_kwargs`` holds a keyword the policy does not take, naming it, its close matches
    and the policy's keywords (SB3 would raise Python's own ``TypeError`` from deep inside the model's setup). A policy
    that takes any keyword, or a ``policy`` that names no one class, is not checked.
    """
    policy_classes = _policy_classes(algorithm, policy)
    if not isinstance(policy_kwargs, Mapping) or len(policy_classes) != 1:
        return
    (policy_class,) = policy_classes
    accepted, closed = _policy_keywords(policy_class)
    if not closed:
        return
    unknown = [keyword for keyword in policy_kwargs if keyword not in accepted]
    if not unknown:
        return
    sentences = [f"{policy_class.__name__}, {algorithm.__name__}'s policy, got {_quoted(unknown, 'and')} in policy_kwargs."]
    for keyword in unknown:
        if close := difflib.get_close_matches(keyword, accepted, n=N_CLOSE_MATCHES):
            sentences.append(f"Did you mean {_quoted(close)}{'' if len(unknown) == 1 else f' for {keyword!r}'}?")
    sentences.append(f"Its keyword arguments are: {', '.join(accepted)}")
    raise UnknownKeywordError(" ".join(sentences))


def _policy_classes(algorithm: type, policy: Any) -> list[type]:
    """The policy class ``policy`` names for ``algorithm``; every one of its aliases' when it names none."""
    aliases: Mapping[str, type] = getattr(algorithm, "policy_aliases", {})
    if isinstance(policy, type):
        return [policy]
    if isinstance(policy, str) and policy in aliases:
        return [aliases[policy]]
    return list(dict.fromkeys(aliases.values()))


def _quoted(names: Iterable[str], conjunction: str = "or") -> str:
    """``'a'``, ``'a' or 'b'``, ``'a', 'b' or 'c'`` (or ``and``)."""
    quoted = [repr(name) for name in names]
    return quoted[0] if len(quoted) == 1 else f"{', '.join(quoted[:-1])} {conjunction} {quoted[-1]}"


class UnknownKeywordError(TypeError):
    """
    A keyword argument an algorithm does not take (Python's own ``TypeError`` for it, with the names it does take): a
    user's mistake, which a command line says in one line.
    """


def check_keywords(
    algorithm: type,
    keywords: Mapping[str, Any],
    policy: Any = None,
    signature: inspect.Signature | None = None,
) -> None:
    """
    Raise ``TypeError`` if a keyword argument is not one of the algorithm's: the message names each such keyword,
    with its close matches (``difflib.get_close_matches``) or, for an argument of the policy, the ``policy_kwargs``
    that takes it, then lists every keyword the algorithm takes (those starting with ``_`` are accepted, not listed).

    :param algorithm: the algorithm class being built (its name and ``policy_aliases``)
    :param keywords: the keyword arguments of the call, by name
    :param policy: the ``policy`` argument of the call (an alias or a class), for the policy's own arguments
    :param signature: the constructor's signature without ``self``; None: ``inspect.signature(algorithm)``
    """
    accepted = keyword_names(inspect.signature(algorithm) if signature is None else signature)
    if accepted is None:
        return
    unknown = [keyword for keyword in keywords if keyword not in accepted]
    if not unknown:
        return
    name = algorithm.__name__
    policy_classes = _policy_classes(algorithm, policy)
    sentences = [
        f"{name} got an unexpected keyword argument {unknown[0]!r}."
        if len(unknown) == 1
        else f"{name} got unexpected keyword arguments {_quoted(unknown, 'and')}."
    ]
    for keyword in unknown:
        owners = [policy_class.__name__ for policy_class in policy_classes if keyword in policy_keyword_names(policy_class)]
        if owners:
            value = repr(keywords[keyword])
            value = value if len(value) <= _MAX_VALUE_LENGTH else "..."
            sentences.append(
                f"{keyword!r} is an argument of the policy ({' or '.join(owners)}), not of {name}: pass it in "
                f"policy_kwargs, e.g. policy_kwargs=dict({keyword}={value})."
            )
        elif close := difflib.get_close_matches(keyword, accepted, n=N_CLOSE_MATCHES):
            sentences.append(f"Did you mean {_quoted(close)}{'' if len(unknown) == 1 else f' for {keyword!r}'}?")
    public = [keyword for keyword in accepted if not keyword.startswith("_")]
    sentences.append(f"{name}'s keyword arguments are: {', '.join(public)}")
    raise UnknownKeywordError(" ".join(sentences))


def checks_keywords(init: InitT) -> InitT:
    """
    Decorate an algorithm's ``__init__`` so that an unknown keyword raises :func:`check_keywords`'s ``TypeError``
    before the call (Python's own names neither the keywords allowed nor the policy's). The signature stays
    ``__init__``'s (``functools.wraps``: ``inspect.signature`` reads it); errors raised within ``__init__`` are its own.
    """
    parameters = list(inspect.signature(init).parameters.values())
    signature = inspect.Signature(parameters[1:])  # without self

    @functools.wraps(init)
    def checked(self: Any, *args: Any, **kwargs: Any) -> None:
        # The class built, or, when it has a constructor of its own that calls this one, the class this one is of
        algorithm = type(self)
        if algorithm.__init__ is not checked:
            algorithm = next(cls for cls in algorithm.__mro__ if cls.__dict__.get("__init__") is checked)
        policy = args[0] if args else kwargs.get("policy")
        check_keywords(algorithm, kwargs, policy, signature)
        if algorithm is type(self):
            # The policy the model builds is its own class's (IET's, not MASAC's when IET calls MASAC's constructor)
            check_policy_keywords(algorithm, policy, kwargs.get("policy_kwargs"))
        init(self, *args, **kwargs)

    return cast(InitT, checked)


def constructor_arguments(frame_locals: dict[str, Any]) -> dict[str, Any]:
    """
    A constructor's arguments by name, from its ``locals()`` before it binds a name of its own (``self`` and the
    ``__class__`` cell left out): how a constructor that writes out its SB3 algorithm's parameters hands them on.
    """
    return {name: value for name, value in frame_locals.items() if name not in ("self", "__class__")}


def check_gymnasium_env(algorithm: str, env: Any, multi_agent: bool) -> None:
    """
    Raise ``TypeError`` for a PettingZoo env (``ParallelEnv`` or ``AECEnv``), saying how to make it a Gymnasium env:
    SB3 would take it for an old Gym env and ask to install Gym.

    :param algorithm: the algorithm's name
    :param env: the ``env`` argument
    :param multi_agent: whether the algorithm trains CTDE envs (``"CTDEPolicy"``); else the message says it is single-agent
    """
    if isinstance(env, AECEnv):
        got = f"the PettingZoo AEC env {type(env).__name__} (agents acting in turns)"
        convert = (
            "convert it to a parallel env with pettingzoo.utils.aec_to_parallel(env) (or make it with its module's "
            "parallel_env(...)), then "
        )
    elif isinstance(env, ParallelEnv):
        got, convert = f"the PettingZoo ParallelEnv {type(env).__name__}", ""
    else:
        return
    wrap = (
        "wrap it as sb3_sera.CTDEEnv(parallel_env) (one Gymnasium env: a Dict observation with the state and each "
        "agent's observation, one Box action joining the agents' actions, the team reward)"
    )
    if multi_agent:
        advice = f"{convert}{wrap} and train it with policy='CTDEPolicy'"
    else:
        advice = (
            f"{algorithm} is single-agent. For a multi-agent task, {convert}{wrap} and train it with an algorithm that "
            "takes policy='CTDEPolicy' (SERASAC and the multi-agent algorithms)"
        )
    raise TypeError(f"{algorithm} got {got}, but SB3 algorithms train Gymnasium envs: {advice}.")


def warn_if_device_unavailable(requested: Any, device: Any) -> None:
    """
    Warn where the device asked for (``requested``, e.g. ``"cuda"``) is not the one the model got (``device``): SB3
    falls back to the CPU without a word when CUDA is missing. ``"auto"`` is never warned about.
    """
    import warnings

    import torch as th

    if str(requested) == "auto":
        return
    if th.device(requested).type != th.device(device).type:
        warnings.warn(
            f"device={str(requested)!r} is not available on this machine: the model trains on {str(device)!r}",
            UserWarning,
            stacklevel=3,
        )
