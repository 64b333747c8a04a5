"""
The library's optional dependencies: rl-zoo3 (with Optuna and its Hugging Face integration) comes only with the
``zoo`` extra, ``pip install "sb3-sera[zoo]"``. ``import sb3_sera`` and ``learn()`` never import it; the functions
that do (:func:`sb3_sera.zoo.register`, the ``-optimize`` search spaces of :mod:`sb3_sera.common.tuning`) import it
on first use through :func:`needs_zoo_extra`, which tells a user without it what to install.
"""

from collections.abc import Iterator
from contextlib import contextmanager

#: The install command that brings rl-zoo3 with the library
ZOO_INSTALL = 'pip install "sb3-sera[zoo]"'


@contextmanager
def needs_zoo_extra(needed_by: str) -> Iterator[None]:
    """
    Import rl-zoo3's modules in this block, and turn a missing one into an ``ImportError`` that names ``needed_by``
    and the fix (``pip install "sb3-sera[zoo]"``), in place of a bare ``ModuleNotFoundError``::

        with needs_zoo_extra("sb3_sera.zoo.register()"):
            from rl_zoo3 import utils

    :param needed_by: what needs rl-zoo3, as a user calls it
    :raises ImportError: where rl-zoo3, or a module it imports, is not installed
    """
    try:
        yield
    except ModuleNotFoundError as error:
        raise ImportError(
            f"{needed_by} needs rl-zoo3 (missing module: {error.name}), which is included if you install sb3-sera with "
            f"its zoo extra: {ZOO_INSTALL}",
            name=error.name,
        ) from error
