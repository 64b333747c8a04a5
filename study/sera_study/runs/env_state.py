"""
An environment's state as plain data, for checkpoints that a new process can load whatever it has imported.

:func:`capture` walks the environment's objects (the vectorized env, its wrappers, the simulator, any object they
hold) and keeps their state as data: numbers, strings, NumPy arrays and containers of them, each random generator's
state, and a MuJoCo simulation's integration state (``mj_getState``: time, ``qpos``, ``qvel``, ``act``, the warm
start, controls and applied forces, everything ``mj_step`` reads). Classes are kept by name only, to check that the
state goes back where it came from. Code, constants and rendering are left out: functions and classes, the compiled
MuJoCo model, pygame's and MuJoCo's renderers, a monitor's open file. :func:`restore` writes such a state into an
environment built anew by the run's own factory, which supplies everything left out.

An object whose state lives outside Python (Box2D's and pymunk's worlds, for example) cannot be captured: the walk
raises :class:`StateNotCapturable` naming where it met it. :func:`check_round_trip` catches what the walk misses, state
that is captured but does not go back: a checkpoint takes it once, at the run's first.

:func:`dump_data` and :func:`load_data` write and read such data with pickle, the reader refusing anything but
Python's containers and NumPy's arrays, scalars and dtypes: a checkpoint never names a class of the code that wrote it.
"""

import copy
import functools
import io
import pickle
import random
import types
from collections import OrderedDict, deque
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import VecEnvWrapper

#: Values kept as they are
_LEAVES = (type(None), bool, int, float, complex, str, bytes, slice, range, np.generic, np.dtype)
#: Containers kept as they are when they hold only plain data (exact types: a subclass would be pickled by name)
_CONTAINERS = (list, tuple, set, frozenset, deque, dict, OrderedDict)
#: Code, not state
_CODE = (
    types.FunctionType,
    types.BuiltinFunctionType,
    types.MethodType,
    types.BuiltinMethodType,
    types.ModuleType,
    functools.partial,
    type,
)
#: Packages whose objects render, never simulate: a new environment's own serve
_RENDERING = ("pygame", "gymnasium.envs.mujoco.mujoco_rendering")
#: Packages whose objects keep their state in C, out of reach of a walk over Python attributes
_OPAQUE = ("Box2D", "pymunk")
#: Types that describe the task, never its state: the compiled MuJoCo model, Gymnasium's registration (which a
#: wrapper caches when first asked)
_CONSTANTS = (
    "mujoco._structs.MjModel",
    "gymnasium.envs.registration.EnvSpec",
    "gymnasium.envs.registration.WrapperSpec",
)
#: Attributes that hold no state of the environment: a monitor's file (a checkpoint reopens it), the members of a
#: VecEnv wrapper's class (SB3 keeps them on the instance)
_NOT_STATE = ((Monitor, "results_writer"), (VecEnvWrapper, "class_attributes"))
#: How deep the walk goes before it gives up on an object graph
MAX_DEPTH = 100


class StateNotCapturable(TypeError):
    """An environment holds state that cannot be written as plain data; the message names where."""


class StateMismatch(ValueError):
    """A captured state does not fit the environment it is written into; the message names where."""


def _type_name(value: Any) -> str:
    return f"{type(value).__module__}.{type(value).__qualname__}"


def _is_plain(value: Any) -> bool:
    if isinstance(value, _LEAVES):
        return True
    if isinstance(value, np.ndarray):
        return value.dtype != object
    if type(value) in (dict, OrderedDict):
        return all(_is_plain(key) and _is_plain(item) for key, item in value.items())
    if type(value) in _CONTAINERS:
        return all(_is_plain(item) for item in value)
    return False


def _skipped(owner: Any, name: str, value: Any) -> bool:
    if any(isinstance(owner, cls) and name == attribute for cls, attribute in _NOT_STATE):
        return True
    return isinstance(value, _CODE) or type(value).__module__.startswith(_RENDERING) or _type_name(value) in _CONSTANTS


def capture(env: Any, name: str = "env") -> Any:
    """
    The state of ``env`` as plain data (see the module's docstring).

    :param name: how messages name ``env``
    :raises StateNotCapturable: where ``env`` holds state that cannot be written as data
    """
    seen: set[int] = set()

    def walk(value: Any, path: str, depth: int) -> Any:
        if _is_plain(value):
            return ("value", copy.deepcopy(value))
        if id(value) in seen:
            return ("seen",)
        if depth > MAX_DEPTH:
            raise StateNotCapturable(f"{path}: objects nested over {MAX_DEPTH} deep, not walked as data")
        if type(value).__module__.split(".")[0] in _OPAQUE:
            raise StateNotCapturable(f"{path} is a {_type_name(value)}, whose state lives in C, not in data")
        seen.add(id(value))
        if isinstance(value, np.random.Generator):
            return ("generator", copy.deepcopy(value.bit_generator.state))
        if isinstance(value, np.random.RandomState):
            return ("random_state", value.get_state(legacy=False))
        if isinstance(value, random.Random):
            return ("python_random", value.getstate())
        if _type_name(value) == "mujoco._structs.MjData":
            return ("mujoco", _mujoco_state(value))
        if type(value) in (list, tuple, deque):
            return ("sequence", [walk(item, f"{path}[{index}]", depth + 1) for index, item in enumerate(value)])
        if type(value) in (dict, OrderedDict):
            if not all(_is_plain(key) for key in value):
                raise StateNotCapturable(f"{path}: a dict whose keys are not plain data")
            return ("mapping", {key: walk(item, f"{path}[{key!r}]", depth + 1) for key, item in value.items()})
        attributes = getattr(value, "__dict__", None)
        if attributes is None:
            raise StateNotCapturable(f"{path} is a {_type_name(value)}, which cannot be written as data")
        kept = {
            key: ("skipped",) if _skipped(value, key, item) else walk(item, f"{path}.{key}", depth + 1)
            for key, item in attributes.items()
        }
        return ("object", type(value).__qualname__, kept)

    return walk(env, name, 0)


def _mujoco_state(data: Any) -> np.ndarray:
    import mujoco

    spec = mujoco.mjtState.mjSTATE_INTEGRATION
    state = np.empty(mujoco.mj_stateSize(data.model, spec))
    mujoco.mj_getState(data.model, data, state, spec)
    return state


def restore(env: Any, state: Any, name: str = "env") -> None:
    """
    Write ``state`` (from :func:`capture`) into ``env``, an environment built as the captured one was.

    :raises StateMismatch: where ``env`` is not laid out as the captured environment was
    """
    restorer = _Restorer()
    restorer.put(env, state, name)
    # Last: an array written before may be a view of a simulation's own
    if restorer.simulations:
        import mujoco

        for data, values in restorer.simulations:
            mujoco.mj_setState(data.model, data, values, mujoco.mjtState.mjSTATE_INTEGRATION)


class _Restorer:
    """Writes a captured state into an environment, node by node; a MuJoCo simulation's state is left for last."""

    def __init__(self) -> None:
        self.simulations: list[tuple[Any, np.ndarray]] = []

    def put(self, target: Any, node: Any, path: str) -> None:
        kind = node[0]
        if kind in ("seen", "skipped"):
            return
        if kind == "generator":
            _expect(isinstance(target, np.random.Generator), path, "a NumPy generator", target)
            target.bit_generator.state = node[1]
        elif kind == "random_state":
            _expect(isinstance(target, np.random.RandomState), path, "a NumPy RandomState", target)
            target.set_state(node[1])
        elif kind == "python_random":
            _expect(isinstance(target, random.Random), path, "a random.Random", target)
            target.setstate(node[1])
        elif kind == "mujoco":
            _expect(_type_name(target) == "mujoco._structs.MjData", path, "a MuJoCo simulation", target)
            self.simulations.append((target, node[1]))
        elif kind == "sequence":
            self.put_sequence(target, node[1], path)
        elif kind == "mapping":
            self.put_mapping(target, node[1], path)
        else:
            self.put_object(target, node[1], node[2], path)

    def put_sequence(self, target: Any, items: list[Any], path: str) -> None:
        _expect(type(target) in (list, tuple, deque), path, "a sequence", target)
        _expect(len(target) == len(items), path, f"{len(items)} items", f"{len(target)} items")
        for index, item in enumerate(items):
            if item[0] != "value":
                self.put(target[index], item, f"{path}[{index}]")
            elif not _same(target[index], item[1]):
                _expect(type(target) is not tuple, path, "a mutable sequence", target)
                target[index] = copy.deepcopy(item[1])

    def put_mapping(self, target: Any, items: dict[Any, Any], path: str) -> None:
        _expect(type(target) in (dict, OrderedDict), path, "a dict", target)
        _expect(list(target) == list(items), path, f"keys {list(items)}", f"keys {list(target)}")
        for key, item in items.items():
            if item[0] == "value":
                target[key] = copy.deepcopy(item[1])
            else:
                self.put(target[key], item, f"{path}[{key!r}]")

    def put_object(self, target: Any, qualname: str, attributes: dict[str, Any], path: str) -> None:
        _expect(type(target).__qualname__ == qualname, path, f"a {qualname}", target)
        for key, item in attributes.items():
            if item[0] == "value":
                _assign(target, key, item[1])
            elif item[0] == "generator" and getattr(target, key, None) is None:
                # Made at the first reset: a new environment has none yet
                setattr(target, key, _generator(item[1]))
            else:
                _expect(hasattr(target, key), f"{path}.{key}", "an attribute", "none")
                self.put(getattr(target, key), item, f"{path}.{key}")


def _generator(state: dict[str, Any]) -> np.random.Generator:
    """A NumPy generator in ``state`` (its bit generator named there: one of NumPy's)."""
    bit_generator = getattr(np.random, state["bit_generator"], None)
    if not (isinstance(bit_generator, type) and issubclass(bit_generator, np.random.BitGenerator)):
        raise StateMismatch(f"{state['bit_generator']!r} is not one of NumPy's bit generators")
    generator = np.random.Generator(bit_generator())
    generator.bit_generator.state = state
    return generator


def _assign(target: Any, key: str, value: Any) -> None:
    """Set ``target.key`` to ``value``: in place for an array of the same layout (its views see it), else anew."""
    current = getattr(target, key, None)
    if (
        isinstance(value, np.ndarray)
        and isinstance(current, np.ndarray)
        and current.shape == value.shape
        and current.dtype == value.dtype
        and current.flags.writeable
    ):
        current[...] = value
    else:
        setattr(target, key, copy.deepcopy(value))


def _expect(condition: bool, path: str, expected: str, found: Any) -> None:
    if not condition:
        found = found if isinstance(found, str) else f"a {_type_name(found)}"
        raise StateMismatch(f"{path}: the saved state needs {expected} there, the environment has {found}")


def _same(a: Any, b: Any) -> bool:
    """Whether two plain values (or captured states) are equal, arrays element by element (NaN equal to NaN)."""
    return difference(a, b) is None


def difference(a: Any, b: Any, path: str = "env") -> str | None:
    """Where two captured states (or plain values) first differ, or None where they are equal."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        same = (
            isinstance(a, np.ndarray)
            and isinstance(b, np.ndarray)
            and a.dtype == b.dtype
            and np.array_equal(a, b, equal_nan=a.dtype.kind in "fc")
        )
        return None if same else path
    if type(a) is not type(b):
        return path
    if isinstance(a, dict):
        if list(a) != list(b):
            return path
        return next((d for key in a if (d := difference(a[key], b[key], f"{path}[{key!r}]")) is not None), None)
    if isinstance(a, list | tuple | deque):
        if len(a) != len(b):
            return path
        pairs = enumerate(zip(a, b, strict=True))
        return next((d for i, (x, y) in pairs if (d := difference(x, y, f"{path}[{i}]")) is not None), None)
    if isinstance(a, float) and a != a and b != b:  # NaN
        return None
    return None if a == b else path


def state_difference(a: Any, b: Any, path: str = "env") -> str | None:
    """
    Where two states from :func:`capture` first differ, named as the environment's attributes, or None (what one
    of them left out, such as a cache one environment has filled and the other not, is no difference).
    """
    if ("skipped",) in (a, b):
        return None
    if not (isinstance(a, tuple) and isinstance(b, tuple) and a[:1] == b[:1]):
        return path
    kind = a[0]
    if kind == "object":
        if a[1] != b[1] or list(a[2]) != list(b[2]):
            return path
        items = [(f"{path}.{key}", a[2][key], b[2][key]) for key in a[2]]
    elif kind == "sequence":
        if len(a[1]) != len(b[1]):
            return path
        items = [(f"{path}[{index}]", x, y) for index, (x, y) in enumerate(zip(a[1], b[1], strict=True))]
    elif kind == "mapping":
        if list(a[1]) != list(b[1]):
            return path
        items = [(f"{path}[{key!r}]", a[1][key], b[1][key]) for key in a[1]]
    else:
        return difference(a[-1], b[-1], path) if len(a) == len(b) == 2 else difference(a, b, path)
    return next((where for sub, x, y in items if (where := state_difference(x, y, sub)) is not None), None)


@contextmanager
def preserved_global_generators() -> Iterator[None]:
    """Put Python's, NumPy's and torch's global generators back as they were after the block."""
    import torch as th

    python, numpy, torch = random.getstate(), np.random.get_state(), th.get_rng_state()
    try:
        yield
    finally:
        random.setstate(python)
        np.random.set_state(numpy)
        th.set_rng_state(torch)


def check_round_trip(env: Any, fresh: Any, name: str = "env") -> Any:
    """
    The state of ``env``, checked to go back whole into ``fresh``, an environment built as ``env`` was (and left
    holding that state).

    :raises StateNotCapturable: where the state cannot be captured, or where ``fresh`` does not take it whole
    """
    state = capture(env, name)
    try:
        restore(fresh, state, name)
    except StateMismatch as error:
        raise StateNotCapturable(f"the saved state does not go back into a new environment: {error}") from None
    where = state_difference(state, capture(fresh, name), name)
    if where is not None:
        raise StateNotCapturable(f"the saved state does not go back into a new environment ({where} differs)")
    return state


#: What :func:`load_data` lets a file name: Python's containers and NumPy's arrays, scalars and dtypes
_ALLOWED = {
    ("builtins", "set"),
    ("builtins", "frozenset"),
    ("builtins", "slice"),
    ("builtins", "range"),
    ("builtins", "complex"),
    ("builtins", "bytearray"),
    ("collections", "deque"),
    ("collections", "OrderedDict"),
    ("numpy", "dtype"),
    ("numpy", "ndarray"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "scalar"),
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.numeric", "_frombuffer"),
    ("numpy.core.numeric", "_frombuffer"),
}


class _DataUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        if (module, name) not in _ALLOWED and not (module == "numpy.dtypes" and name.endswith("DType")):
            raise pickle.UnpicklingError(f"{module}.{name} is not plain data: a checkpoint holds data, never classes")
        return super().find_class(module, name)


def dump_data(data: Any, path: Path, check: bool = True) -> None:
    """
    Write ``data`` (plain data only, as :func:`load_data` reads back) to ``path``.

    :param check: read it back first as :func:`load_data` would, refusing a class at writing, never at reading (off
        for a large file of arrays alone, such as a replay buffer's)
    """
    payload = pickle.dumps(data, protocol=pickle.HIGHEST_PROTOCOL)
    if check:
        _DataUnpickler(io.BytesIO(payload)).load()
    path.write_bytes(payload)


def load_data(path: Path) -> Any:
    """Read what :func:`dump_data` wrote; ``pickle.UnpicklingError`` names a class the file would need."""
    with path.open("rb") as handle:
        return _DataUnpickler(handle).load()
