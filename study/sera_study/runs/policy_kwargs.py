"""
``policy_kwargs`` written as text (a YAML entry or ``-params policy_kwargs:...``), read without executing code.

rl-zoo3 writes them as Python (``dict(net_arch=[256, 256], activation_fn=nn.ReLU)``) and passes the text to
``eval``, so a hyperparameter file or a command line could run anything. This parser accepts only literals (numbers,
strings, booleans, None, lists, tuples, dicts), ``dict(key=value, ...)`` and the names of :data:`NAMES`, and refuses
everything else with the part it refused; :func:`parse_value` reads any other ``-params`` value as a literal or as
its own text.
"""

import ast
from typing import Any

import torch as th
from torch import nn

#: The names a policy_kwargs text may use: activation functions, optimizers and feature extractors' building blocks
NAMES: dict[str, Any] = {
    **{f"nn.{name}": getattr(nn, name) for name in ("ReLU", "Tanh", "ELU", "LeakyReLU", "GELU", "SiLU", "Sigmoid", "Mish")},
    **{f"th.optim.{name}": getattr(th.optim, name) for name in ("Adam", "AdamW", "RMSprop", "SGD")},
}
NAMES.update({f"torch.{name[3:]}": value for name, value in list(NAMES.items()) if name.startswith("th.")})
NAMES.update({"True": True, "False": False, "None": None})


def _dotted(node: ast.expr) -> str | None:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        parent = _dotted(node.value)
        return None if parent is None else f"{parent}.{node.attr}"
    return None


def _value(node: ast.expr, text: str) -> Any:
    if isinstance(node, ast.Constant):
        return node.value
    if (
        isinstance(node, ast.UnaryOp)
        and isinstance(node.op, ast.USub)
        and isinstance(node.operand, ast.Constant)
        and isinstance(node.operand.value, int | float)
    ):
        return -node.operand.value
    if isinstance(node, ast.List | ast.Tuple):
        items = [_value(item, text) for item in node.elts]
        return items if isinstance(node, ast.List) else tuple(items)
    if isinstance(node, ast.Dict):
        if any(key is None for key in node.keys):
            raise ValueError(f"policy_kwargs {text!r}: '**' unpacking is not allowed")
        return {_value(key, text): _value(value, text) for key, value in zip(node.keys, node.values, strict=True)}  # type: ignore[arg-type]
    if isinstance(node, ast.Call) and _dotted(node.func) == "dict" and not node.args:
        if any(keyword.arg is None for keyword in node.keywords):
            raise ValueError(f"policy_kwargs {text!r}: '**' unpacking is not allowed")
        return {keyword.arg: _value(keyword.value, text) for keyword in node.keywords}
    name = _dotted(node)
    if name is not None and name in NAMES:
        return NAMES[name]
    raise ValueError(
        f"policy_kwargs {text!r}: {ast.get_source_segment(text, node) or type(node).__name__!r} is not allowed; "
        f"write literals, dict(key=value) and these names only: {sorted(NAMES)}"
    )


def parse_policy_kwargs(text: str) -> dict[str, Any]:
    """
    ``policy_kwargs`` from their text, without executing it (see the module's docstring).

    :raises ValueError: for anything but literals, ``dict(...)`` and the names of :data:`NAMES`, or a result that is
        not a dict
    """
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except SyntaxError as error:
        raise ValueError(f"policy_kwargs {text!r} is not a Python expression: {error.msg}") from None
    value = _value(tree.body, text.strip())
    if not isinstance(value, dict):
        raise ValueError(f"policy_kwargs {text!r} must be a dict, got {type(value).__name__}")
    return value


def parse_value(text: str) -> Any:
    """A ``-params`` value as rl-zoo3 reads it (a Python literal, else the string itself: ``lin_3e-4``), never run."""
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text
