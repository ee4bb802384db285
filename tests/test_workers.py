"""Scale-out generation: every (task, seed) exactly once, across failures, dead workers, kills and resumes.

The episode functions are module-level so spawned workers (and Ray workers) can import them by name.
"""

import os
import signal
import subprocess
import sys
import time
import warnings
from collections import Counter
from pathlib import Path

import pytest

from datagen.store import Dataset
from datagen.workers import episode_keys, generate, synthetic_episode

TESTS = Path(__file__).parent


def flaky_episode(task: str, seed: int):
    if seed % 3 == 1:
        raise ValueError(f"planner gave up on {task} {seed}")
    return synthetic_episode(task, seed)


def dying_episode(task: str, seed: int):
    """Kills its own worker process on ('a', 2), once (a marker file remembers), like a segfault would."""
    marker = Path(os.environ["SUDD_TEST_MARKER"])
    if (task, seed) == ("a", 2) and not marker.exists():
        marker.touch()
        os.kill(os.getpid(), signal.SIGKILL)
    return synthetic_episode(task, seed)


def slow_episode(task: str, seed: int):
    time.sleep(0.15)
    return synthetic_episode(task, seed)


def stored_keys(out) -> Counter:
    ds = Dataset(out)
    return Counter((r["task"], r["seed"]) for r in ds.episodes())


def test_pool_generates_every_key_once(tmp_path):
    out = tmp_path / "data"
    s = generate(["a", "b"], 4, out, workers=2, episode_fn=synthetic_episode, seed_offset=10, progress=False)
    expected = set(episode_keys(["a", "b"], 4, 10))
    assert stored_keys(out) == Counter(expected)
    assert sorted(Dataset(out).shards) == ["w000", "w001"]
    assert (s["requested"], s["skipped"], s["episodes"], s["errors"], s["total"]) == (8, 0, 8, 0, 8)
    assert s["per_task"]["a"]["episodes"] == s["per_task"]["b"]["episodes"] == 4
    assert s["successes"] == sum(bool(r["success"]) for r in Dataset(out).episodes())
    assert s["episodes_per_hour"] > 0 and s["wall_s"] > 0 and s["backend"] == "process"
    again = generate(["a", "b"], 4, out, workers=2, episode_fn=synthetic_episode, seed_offset=10, progress=False)
    assert (again["skipped"], again["episodes"]) == (8, 0)
    more = generate(["a"], 5, out, workers=2, episode_fn=synthetic_episode, seed_offset=10, progress=False)
    assert (more["requested"], more["skipped"], more["episodes"], more["workers"]) == (5, 4, 1, 1)
    assert stored_keys(out) == Counter(expected | {("a", 14)})


def test_given_seeds_replace_the_range_for_every_task(tmp_path):
    out = tmp_path / "data"
    s = generate(["a", "b"], 0, out, workers=2, episode_fn=synthetic_episode, seeds=[7, 3], progress=False)
    assert stored_keys(out) == Counter([("a", 7), ("a", 3), ("b", 7), ("b", 3)])
    assert (s["requested"], s["episodes"]) == (4, 4)
    again = generate(["a"], 0, out, workers=1, episode_fn=synthetic_episode, seeds=[3, 4], progress=False)
    assert (again["skipped"], again["episodes"]) == (1, 1) and stored_keys(out)[("a", 4)] == 1


def test_failing_episodes_are_counted_then_resumed(tmp_path, caplog):
    out = tmp_path / "data"
    s = generate(["a", "b"], 6, out, workers=2, episode_fn=flaky_episode, progress=False)
    failing = {(t, k) for t in "ab" for k in range(6) if k % 3 == 1}
    assert s["errors"] == len(failing) == 4 and s["episodes"] == 8
    assert {(e["task"], e["seed"]) for e in s["error_keys"]} == failing
    assert all("planner gave up" in e["error"] for e in s["error_keys"])
    assert s["per_task"]["a"] == {"episodes": 4, "successes": s["per_task"]["a"]["successes"], "errors": 2}
    assert "episode (a, 1) failed" in caplog.text
    resumed = generate(["a", "b"], 6, out, workers=2, episode_fn=synthetic_episode, progress=False)
    assert (resumed["skipped"], resumed["episodes"], resumed["total"]) == (8, 4, 12)
    assert stored_keys(out) == Counter(episode_keys(["a", "b"], 6))


def test_dead_worker_loses_only_its_episode(tmp_path, monkeypatch):
    out = tmp_path / "data"
    monkeypatch.setenv("SUDD_TEST_MARKER", str(tmp_path / "died"))
    s = generate(["a"], 6, out, workers=2, episode_fn=dying_episode, progress=False)
    assert s["errors"] == 1 and s["error_keys"][0]["seed"] == 2 and "died" in s["error_keys"][0]["error"]
    assert stored_keys(out) == Counter(k for k in episode_keys(["a"], 6) if k != ("a", 2))
    resumed = generate(["a"], 6, out, workers=2, episode_fn=dying_episode, progress=False)
    assert (resumed["skipped"], resumed["episodes"]) == (5, 1)
    assert stored_keys(out) == Counter(episode_keys(["a"], 6))


def test_killed_run_resumes_without_duplicates_or_losses(tmp_path):
    """SIGKILL the whole run (parent and workers, mid-episode or mid-append), then re-run the command."""
    out = tmp_path / "data"
    code = ("from datagen.workers import generate; from test_workers import slow_episode\n"
            f"generate(['a', 'b'], 10, {str(out)!r}, workers=2, episode_fn=slow_episode, progress=False)\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.Popen([sys.executable, "-c", code], env=env, start_new_session=True)
    try:
        deadline = time.monotonic() + 30
        committed = 0
        while committed < 4 and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)
            if (out / "shards").is_dir():
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    committed = len(Dataset(out))
        assert proc.poll() is None, "the run finished before it could be killed"
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    before = stored_keys(out)
    assert 4 <= sum(before.values()) < 20 and max(before.values()) == 1
    s = generate(["a", "b"], 10, out, workers=2, episode_fn=synthetic_episode, progress=False)
    assert s["skipped"] == sum(before.values()) and s["errors"] == 0 and s["total"] == 20
    ds = Dataset(out, verify=True)
    assert stored_keys(out) == Counter(episode_keys(["a", "b"], 10)) and not ds.skipped
    assert ds.num_steps == sum(r["length"] for r in ds.episodes())


def test_ray_backend(tmp_path):
    ray = pytest.importorskip("ray", reason="ray is not installed (pip install ray) - the Ray path is untested")
    try:
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False,
                 runtime_env={"env_vars": {"PYTHONPATH": str(TESTS)}})
    except Exception as exc:  # no shared memory, sandboxed ports, ...
        pytest.skip(f"a local Ray instance could not start: {type(exc).__name__}: {exc}")
    try:
        out = tmp_path / "data"
        s = generate(["a", "b"], 3, out, workers=2, episode_fn=flaky_episode, ray_address="auto", progress=False)
        assert s["backend"] == "ray" and s["episodes"] == 4 and s["errors"] == 2
        resumed = generate(["a", "b"], 3, out, workers=2, episode_fn=synthetic_episode, ray_address="auto",
                           progress=False)
        assert (resumed["skipped"], resumed["episodes"]) == (4, 2)
        assert stored_keys(out) == Counter(episode_keys(["a", "b"], 3))
    finally:
        ray.shutdown()
