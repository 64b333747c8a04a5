"""Which code made a run: the digest of the code that can change its numbers, and what it leaves out."""

import ast

from stable_baselines3 import SAC

from sb3_sera import MASAC, SERASAC
from sera_study.runs.provenance import _code_text, code_difference, run_code_digest, run_code_modules

CODE = '''
def rate(x):
    """The rate."""
    return 2 * x  # doubled
'''


def test_comments_docstrings_and_layout_do_not_count_but_code_does():
    same = CODE.replace('"""The rate."""', '"""The rate, per step."""').replace("# doubled", "# twice")
    same = same.replace("2 * x", "2*x")
    assert _code_text(ast.parse(CODE)) == _code_text(ast.parse(same))
    assert _code_text(ast.parse(CODE)) != _code_text(ast.parse(CODE.replace("2 * x", "3 * x")))
    # A function that is only a docstring keeps a body
    assert _code_text(ast.parse('def f():\n    """Nothing."""\n')) == _code_text(ast.parse("def f():\n    pass\n"))


def test_a_run_digests_the_modules_its_algorithm_and_task_load_and_the_engine_alone():
    stock = run_code_modules(SAC, "Pendulum-v1")
    sera = run_code_modules(SERASAC, "Pendulum-v1")
    multi_agent = run_code_modules(MASAC, "sb3_sera/HalfCheetah-6x1-v0")
    assert "sera_study.runs.engine" in stock and "sera_study.runs.env_state" in stock
    # Stock SAC's runs do not hang on SERASAC's algorithm nor on the bookkeeping of folders and records
    assert "sb3_sera.sera.sera" not in stock and "sb3_sera.sera.sera" in sera
    # ... nor on SERA's aggregation, which the evaluations' critic diagnostics once imported for their correlations
    assert "sb3_sera.sera.aggregation" not in stock and "sb3_sera.common.correlation" in stock
    assert not {"sb3_sera", "sera_study.runs.folders", "sera_study.records"} & set(stock)
    assert {"sb3_sera.ctde.algorithms", "sb3_sera.ctde.tasks"} <= set(multi_agent) and "sb3_sera.sera.sera" not in multi_agent
    assert len({run_code_digest(SAC, "Pendulum-v1"), run_code_digest(SERASAC, "Pendulum-v1")}) == 2


def test_a_record_of_other_code_is_named_with_what_differs():
    now = {"versions": {"torch": "2.13.0"}, "run_code_digest": "a" * 16, "code_digest": "c" * 16}
    assert code_difference({**now, "code_digest": "d" * 16}, now) is None  # the package's digest alone does not count
    assert code_difference({**now, "run_code_digest": "b" * 16}, now) == (
        f"the code that shapes its numbers had digest {'b' * 16}, now {'a' * 16}"
    )
    assert code_difference({**now, "versions": {"torch": "2.12.0"}}, now) == (
        "package versions differ: torch 2.12.0 then, 2.13.0 now"
    )
    # A record from before the run's digest: the package's digest decides
    older = {key: value for key, value in now.items() if key != "run_code_digest"}
    assert code_difference(older, now) is None
    assert code_difference({**older, "code_digest": "d" * 16}, now).startswith("its code digest is dddd")
