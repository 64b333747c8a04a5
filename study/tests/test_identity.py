"""Code identity of ledger groups run at several commits, from a table of hashes, by hand."""

import yaml

from sera_study.results.identity import CODE_HASHES_FILE, configuration_key, identity_lines, load_code_hashes
from sera_study.results.report import group_runs, load_runs
from study.tests.test_report import fake_run


def _at(folder, commit: str, clean: bool = True) -> None:
    args_file = next(folder.glob("*/args.yml"))
    args_file.write_text(yaml.safe_dump({**yaml.safe_load(args_file.read_text()), "git_commit": commit, "git_clean": clean}))


def test_groups_from_several_commits_say_whether_their_code_trains_the_same(tmp_path):
    hyperparams = {"learning_starts": 100}
    _at(fake_run(tmp_path, "serasac", 1, 0, [1.0, 2.0, 3.0], hyperparams=hyperparams), "a" * 40)
    _at(fake_run(tmp_path, "serasac", 2, 1, [1.0, 3.0, 4.0], hyperparams=hyperparams), "b" * 40)
    _at(fake_run(tmp_path, "masac", 1, 0, [1.0, 2.0, 3.0], hyperparams=hyperparams, algo="masac"), "a" * 40)
    groups = group_runs(load_runs([tmp_path])[0])
    key = configuration_key("serasac", "sb3_sera/HalfCheetah-6x1-v0", {"policy": "CTDEPolicy", **hyperparams})
    assert key.startswith("serasac sb3_sera/HalfCheetah-6x1-v0 ")
    # One commit's runs (masac) need no hash; serasac's two commits are compared
    (line,) = identity_lines(groups, {"a" * 40: {key: "h1"}, "b" * 40: {key: "h1"}})
    assert line == "- serasac: runs 1 at aaaaaaa, 1 at bbbbbbb; the check's run hashes the same at each (h1)."
    (line,) = identity_lines(groups, {"a" * 40: {key: "h1"}, "b" * 40: {key: "h2"}})
    assert "the check's run hashes DIFFERENTLY: aaaaaaa h1, bbbbbbb h2" in line
    (line,) = identity_lines(groups, {"a" * 40: {key: "h1"}})
    assert "not hashed at bbbbbbb" in line
    # A run made from a modified tree is named: no hash of its commit covers it
    _at(next((tmp_path / "serasac").glob("*_2")), "b" * 40, clean=False)
    (line,) = identity_lines(group_runs(load_runs([tmp_path])[0]), {"a" * 40: {key: "h1"}, "b" * 40: {key: "h1"}})
    assert "1 at bbbbbbb (modified tree)" in line and "the tree at bbbbbbb was modified" in line
    # The ledger's table: per commit, per configuration
    assert load_code_hashes(tmp_path) is None
    (tmp_path / CODE_HASHES_FILE).write_text(yaml.safe_dump({"hashes": {"a" * 40: {key: "h1"}}}))
    assert load_code_hashes(tmp_path) == {"a" * 40: {key: "h1"}}
