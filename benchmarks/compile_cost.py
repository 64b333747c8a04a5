"""
What compiling a model's gradient step costs (``compile_update=True``, batches of 32, a buffer of 1,000): the
operations Dynamo traces in it, and the CPU seconds of building the model and making its first gradient step in a
fresh process on one torch thread, the process's own (Dynamo, AOT autograd, Inductor) and its children's (the C++
compiler), cold (Inductor's cache an empty folder) and warm (the same model built again in a new process: every later
build on the machine).

    python benchmarks/compile_cost.py --algo iet --policy CTDEPolicy --env sb3_sera/SimpleSpread-v0
    python benchmarks/compile_cost.py --algo serasac --env Pendulum-v1 --policy-kwargs "{'net_arch': [16]}"

``--cpp-wrapper`` compiles with Inductor's C++ wrapper (``torch._inductor.config.cpp_wrapper``). ``--this-cache``
measures one build on the cache the environment names (``TORCHINDUCTOR_CACHE_DIR``, else Inductor's
default folder), cold or warm as that cache is.
"""

import argparse
import ast
import json
import os
import resource
import subprocess
import sys
import tempfile
from typing import Any


def cpu_seconds() -> tuple[float, float]:
    """User and system CPU seconds so far of this process and of its finished children."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime, children.ru_utime + children.ru_stime


def build(
    algo: str, policy: str, env: str, learning_starts: int, policy_kwargs: dict[str, Any] | None, cpp_wrapper: bool
) -> dict[str, Any]:
    """Build the compiled model, train it to its first gradient step, and say what that cost (this process)."""
    import torch as th
    import torch._inductor.config
    from torch._dynamo.utils import counters

    from sera_study.registry import algorithm_classes

    th.set_num_threads(1)
    before = cpu_seconds()
    algorithm: Any = algorithm_classes()[algo]  # one that takes compile_update (SB3's own refuse it)
    model = algorithm(
        policy,
        env,
        seed=0,
        compile_update=True,
        learning_starts=learning_starts,
        batch_size=32,
        buffer_size=1_000,
        policy_kwargs=policy_kwargs,
    )
    with torch._inductor.config.patch(cpp_wrapper=cpp_wrapper):  # read where the step compiles, at its first call
        model.learn(learning_starts + 1)
    after = cpu_seconds()
    return {
        "operations": counters["stats"]["calls_captured"],
        "own": after[0] - before[0],
        "compiler": after[1] - before[1],
    }


def measure(args: argparse.Namespace, cache: str | None) -> dict[str, Any]:
    """One build in a new Python process, on Inductor's cache in ``cache`` (None: the environment's)."""
    command = [sys.executable, __file__, "--child", "--algo", args.algo, "--policy", args.policy, "--env", args.env]
    command += ["--learning-starts", str(args.learning_starts), "--policy-kwargs", repr(args.policy_kwargs)]
    command += ["--cpp-wrapper"] if args.cpp_wrapper else []
    env = {**os.environ, "OMP_NUM_THREADS": "1", **({"TORCHINDUCTOR_CACHE_DIR": cache} if cache else {})}
    completed = subprocess.run(command, capture_output=True, text=True, env=env, check=False)
    if completed.returncode != 0:
        raise SystemExit(f"the build failed:\n{completed.stderr[-3000:]}")
    return json.loads(completed.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algo", default="serasac", help="an algorithm that compiles its update (default: serasac)")
    parser.add_argument("--policy", default="MlpPolicy", help="MlpPolicy, or CTDEPolicy for a multi-agent task")
    parser.add_argument("--env", default="Pendulum-v1")
    parser.add_argument("--learning-starts", type=int, default=64)
    parser.add_argument("--policy-kwargs", type=ast.literal_eval, help="the model's policy_kwargs, a Python dict literal")
    parser.add_argument("--this-cache", action="store_true", help="one build on the environment's Inductor cache")
    parser.add_argument(
        "--cpp-wrapper", action="store_true", help="Inductor's C++ wrapper (torch._inductor.config.cpp_wrapper)"
    )
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        cost = build(args.algo, args.policy, args.env, args.learning_starts, args.policy_kwargs, args.cpp_wrapper)
        print(json.dumps(cost))
        return
    rows = []
    if args.this_cache:
        rows.append(("the environment's cache", measure(args, None)))
    else:
        with tempfile.TemporaryDirectory(prefix="compile_cost_") as cache:
            rows += [("cold", measure(args, cache)), ("warm", measure(args, cache))]
    wrapper = "C++" if args.cpp_wrapper else "Python"
    print(
        f"{args.algo} ({args.policy}) on {args.env}, policy_kwargs {args.policy_kwargs}, Inductor's {wrapper} wrapper: "
        "CPU seconds of one build"
    )
    print("| build | operations traced | own (Dynamo, AOT, Inductor) | C++ compiler | total |")
    print("|---|---|---|---|---|")
    for name, cost in rows:
        total = cost["own"] + cost["compiler"]
        print(f"| {name} | {cost['operations']} | {cost['own']:.1f} | {cost['compiler']:.1f} | {total:.1f} |")


if __name__ == "__main__":
    main()
