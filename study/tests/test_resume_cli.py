"""
Resuming as users resume: the command line in a process of its own, Ctrl-C (SIGINT to its process group) part way,
then the same command again in a new process, on each kind of task; the run ends as an uninterrupted one does.
"""

import subprocess
import time
from pathlib import Path

import pytest

from sera_study.records import load_result
from sera_study.runs.backends import STOPPED_LOG
from study.tests.helpers import assert_same_end, ctrl_c, killed_at_exit, start_command
from tests.helpers import CTDE_TASK

# A classic-control task, a MuJoCo task, a MaMuJoCo task and a PettingZoo MPE task, with episodes short enough for
# several to end before and after the interruption
TASKS = {
    "classic-control": ("Pendulum-v1", 100),
    "mujoco": ("HalfCheetah-v5", 100),
    "mamujoco": ("sb3_sera/HalfCheetah-6x1-v0", 100),
    "mpe": (CTDE_TASK, 25),
}
STEPS, EVERY = 500, 100


def compare(task: str, episode: int, out: Path, checkpoint_freq: int) -> subprocess.Popen:
    """``sb3-sera compare`` of SERASAC on ``task``, started as a terminal starts it (a process group of its own)."""
    params = [
        "learning_starts:100",
        "batch_size:32",
        "buffer_size:1000",
        "policy_kwargs:dict(net_arch=[32, 32])",
        f"env_kwargs:{{'max_episode_steps': {episode}}}",
    ]
    command = ["compare", "--algos", "serasac", "--env", task, "--seeds", "0", "-n", str(STEPS), "--eval-freq", "200"]
    command += ["--eval-episodes", "1", "--n-jobs", "1", "--num-threads", "1", "--out", str(out)]
    command += ["--checkpoint-freq", str(checkpoint_freq), "-params", *params]
    return start_command(*command)


def finish(process: subprocess.Popen, timeout: float = 300) -> str:
    """Its standard error, once it has ended well."""
    _, stderr = process.communicate(timeout=timeout)
    assert process.returncode == 0, stderr[-3000:]
    return stderr


def interrupt_after_checkpoint(process: subprocess.Popen, out: Path, step: int, timeout: float = 300) -> str:
    """
    Ctrl-C to ``process`` once a run under ``out`` has a checkpoint at ``step`` or later; its standard error, once it
    has ended as an interrupted command ends (exit code 130).
    """
    deadline = time.monotonic() + timeout
    with killed_at_exit(process):
        while time.monotonic() < deadline:
            steps = [int(path.read_text() or 0) for path in out.glob("*/*/checkpoint/step")]
            if steps and max(steps) >= step:
                break
            assert process.poll() is None, process.communicate()[1][-3000:]
            time.sleep(0.05)
        stderr = ctrl_c(process, timeout=60)
    assert process.returncode == 130, stderr[-3000:]
    return stderr


def run_folder(out: Path) -> Path:
    (folder,) = out.glob("serasac/*_1")
    return folder


#: The kinds whose end-to-end check stays out of CI (a minute each): MuJoCo's state is restored in the MaMuJoCo one, an
#: MPE run resumes in study/tests/test_checkpoint.py, and a Pendulum run resumes there and from the command line
#: below (``sb3-sera train``), while the MaMuJoCo kind takes ``compare`` through the same Ctrl-C and resume
SLOW_KINDS = ("classic-control", "mujoco", "mpe")


@pytest.mark.parametrize(
    "kind", [pytest.param(kind, marks=pytest.mark.slow) if kind in SLOW_KINDS else kind for kind in sorted(TASKS)]
)
def test_a_run_interrupted_by_ctrl_c_resumes_from_the_command_line_to_the_uninterrupted_end(tmp_path, kind):
    task, episode = TASKS[kind]
    straight, resumed = tmp_path / "straight", tmp_path / "resumed"
    finish(compare(task, episode, straight, checkpoint_freq=0))
    stderr = interrupt_after_checkpoint(compare(task, episode, resumed, EVERY), resumed, 2 * EVERY)
    assert "Traceback" not in stderr and "the same command resumes serasac seed 0" in stderr
    # The run folder keeps what the interruption said (a piped terminal may lose it), and the next command says what
    # it found and what it did
    a, b = run_folder(straight), run_folder(resumed)
    assert "the same command resumes serasac seed 0" in (b / STOPPED_LOG).read_text()
    said = finish(compare(task, episode, resumed, EVERY))
    (resume,) = load_result(b).resumes
    assert f"{b}: stopped; its last checkpoint is at step {resume['from_step']:,}, written 20" in said
    assert f"{b}: resumed from step {resume['from_step']:,}" in said
    assert resume["from_step"] >= 2 * EVERY
    assert assert_same_end(a, b, f"{task.replace('/', '-')}.zip") >= STEPS // episode - 1
