"""`sudd eval` on the command line: results written and resumed, its options passed to the episodes, bad
arguments refused, Ctrl-C keeping what finished."""

import json

import pytest

PUT = "put the red block in the drawer and close it"  # a drawer_put instruction, for a bundle taught one


def test_eval_cli_writes_results_and_resumes(untrained_bundle, tmp_path, monkeypatch, capsys):
    from runtime.cli import main

    args = ["eval", "--policy", str(untrained_bundle), "--task", "pick_place", "--episodes", "1",
            "--time-limit-factor", "0.03", "--suite", "seen", "--suite", "paraphrase", "--out", str(tmp_path)]
    assert main(args) == 0
    lines = (tmp_path / "results.jsonl").read_text().splitlines()
    got = sorted((json.loads(x)["suite"], json.loads(x)["who"]) for x in lines)
    assert got == [("paraphrase", "policy"), ("seen", "collector"), ("seen", "policy")]
    para = next(json.loads(x) for x in lines if json.loads(x)["suite"] == "paraphrase")
    assert para["command"] != para["instruction"]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert {r["who"] for r in summary["rows"]} == {"policy", "collector"}
    import mujoco
    import onnxruntime

    assert summary["versions"]["mujoco"] == mujoco.__version__  # what the figures were measured on
    assert summary["versions"]["onnxruntime"] == onnxruntime.__version__
    from runtime.machine_record import cpu_description

    assert summary["versions"]["cpu"] == cpu_description()
    md = (tmp_path / "results.md").read_text()
    assert f"Measured on {cpu_description()}, numpy" in md
    assert "| seen | pick_place | 0/1" in md and "| paraphrase | pick_place | 0/1" in md
    assert "Why the policy failed" in md
    assert (tmp_path / "success.png").stat().st_size > 1000
    assert main(args) == 0  # resumed: nothing left to run, nothing appended
    assert len((tmp_path / "results.jsonl").read_text().splitlines()) == 3
    capsys.readouterr()
    monkeypatch.setattr("runtime.machine_record.cpu_description", lambda cpuinfo=None: "Other CPU (avx512f)")
    assert main([*args, "--episodes", "2"]) == 0  # one more seed, resumed on another machine: it says so
    assert len((tmp_path / "results.jsonl").read_text().splitlines()) == 6
    assert "was started on another machine or install (cpu: " in capsys.readouterr().err


def test_eval_cli_runs_exactly_the_listed_seeds(untrained_bundle, tmp_path, capsys):
    from runtime.cli import main

    base = ["eval", "--policy", str(untrained_bundle), "--task", "pick_place", "--no-collector",
            "--time-limit-factor", "0.03"]
    assert main([*base, "--seeds", "100007,100003", "--out", str(tmp_path / "a")]) == 0
    got = [json.loads(x)["seed"] for x in (tmp_path / "a" / "results.jsonl").read_text().splitlines()]
    summary = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert got == [100007, 100003] and summary["seeds"] == got and summary["episodes"] == 2
    assert main([*base, "--seeds", "100007", "--episodes", "3", "--out", str(tmp_path / "b")]) == 2
    assert main([*base, "--seeds", "1x", "--out", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err
    assert "leave out --episodes" in err and "'1x' is not a seed" in err


@pytest.fixture
def episode_kwargs(monkeypatch) -> list[dict]:
    """The keyword arguments of every run_policy_episode call the eval CLI makes (the episodes still run)."""
    import runtime.evaluate

    seen, real = [], runtime.evaluate.run_policy_episode

    def spy(*args, **kw):
        seen.append(kw)
        return real(*args, **kw)

    monkeypatch.setattr(runtime.evaluate, "run_policy_episode", spy)
    return seen


def test_eval_cli_runs_the_episodes_with_the_controller_file(untrained_bundle, tmp_path, episode_kwargs):
    from runtime.cli import main

    toml = tmp_path / "hold.toml"
    toml.write_text("gripper_min_hold = 0.6\n")
    out = tmp_path / "eval"
    assert main(["eval", "--policy", str(untrained_bundle), "--task", "pick_place", "--episodes", "1", "--no-collector",
                 "--time-limit-factor", "0.03", "--controller", str(toml), "--out", str(out)]) == 0
    assert [kw["controller"].gripper_min_hold for kw in episode_kwargs] == [0.6]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["settings"]["controller"]["gripper_min_hold"] == 0.6


def test_eval_cli_passes_a_fixed_latency_speed_and_filmstrips_and_refuses_bad_ones(untrained_bundle, tmp_path,
                                                                                      episode_kwargs, capsys,
                                                                                      monkeypatch):
    from runtime.cli import main
    from sim.tasks import task_of_instruction

    base = ["eval", "--policy", str(untrained_bundle), "--task", "pick_place", "--episodes", "1", "--no-collector",
            "--time-limit-factor", "0.03"]
    assert main([*base, "--latency-ms", "6", "--filmstrips", "--speed", "pick_place=0.5", "--out",
                 str(tmp_path / "a")]) == 0
    assert main([*base, "--out", str(tmp_path / "b")]) == 0
    assert [kw["latency_s"] for kw in episode_kwargs] == [0.006, None]
    assert [kw["speed"] for kw in episode_kwargs] == [0.5, 1.0]  # the untrained bundle records no pace: 1
    (a,), (b,) = (map(json.loads, (tmp_path / d / "results.jsonl").read_text().splitlines()) for d in "ab")
    assert not a["success"] and a["filmstrip"] == str(tmp_path / "a" / "filmstrips" / "seen_pick_place_100000.png")
    assert (tmp_path / "a" / "filmstrips" / "seen_pick_place_100000.png").stat().st_size > 1000
    assert "filmstrip" not in b and not (tmp_path / "b" / "filmstrips").exists()
    settings = json.loads((tmp_path / "a" / "summary.json").read_text())["settings"]
    assert settings["latency_ms"] == 6.0 and settings["pace"] == {"pick_place": 0.5} and a["speed"] == 0.5
    assert "Policy pace (fraction of the recorded speed): pick_place 0.5" in (tmp_path / "a" / "results.md").read_text()
    assert "Goal query: off (the bundle has none)" in (tmp_path / "a" / "results.md").read_text()
    assert [kw["goal_query"] for kw in episode_kwargs] == [True, True]  # on unless --no-goal-query
    assert main([*base, "--no-goal-query", "--out", str(tmp_path / "e")]) == 0
    assert episode_kwargs[-1]["goal_query"] is False
    assert json.loads((tmp_path / "e" / "summary.json").read_text())["settings"]["goal_query"] is False
    assert all(kw["phases"] is None for kw in episode_kwargs)  # one command unless --phases
    assert main([*base, "--task", "drawer_put", "--phases", "--speed", "drawer_open=0.75",
                 "--out", str(tmp_path / "f")]) == 0
    from runtime.phases import Phase

    # the untrained bundle knows no drawer command: as the policy node would, the eval runs it as its closest
    # trained instruction's family, pick_place, and so as one command
    assert [(kw["runs_as"], kw["phases"]) for kw in episode_kwargs[-2:]] == [("pick_place", None)] * 2
    monkeypatch.setattr("runtime.command_family.command_family", lambda bundle, text: task_of_instruction(text))
    assert main([*base, "--task", "drawer_put", "--phases", "--speed", "drawer_open=0.75",
                 "--out", str(tmp_path / "g")]) == 0
    by_task = {kw["phases"] is not None: kw for kw in episode_kwargs[-2:]}  # pick_place, then drawer_put
    assert by_task[True]["runs_as"] == "drawer_put"
    assert by_task[False]["speed"] == 1.0  # pick_place is one command whatever --phases says
    assert by_task[True]["phases"] == [Phase("open the drawer", 0.75, family="drawer_open"),
                                       Phase(None, 1.0, family="drawer_put"),
                                       Phase("close the drawer", 1.0, stage_from=2, family="drawer_close")]
    told = (tmp_path / "g" / "results.md").read_text()
    assert "Run as their phases (runtime/phases.py; --phases): drawer_put" in told
    assert main([*base, "--speed", "drawer_shut=0.5", "--out", str(tmp_path / "d")]) == 2
    assert "--speed.drawer_shut: unknown task family" in capsys.readouterr().err
    assert main([*base, "--latency-ms", "-1", "--out", str(tmp_path / "c")]) == 2
    assert "--latency-ms -1.0: expected 0 <= MS < 1000" in capsys.readouterr().err


def test_eval_cli_runs_the_families_the_bundle_lists_as_phases_unless_told_otherwise(untrained_bundle, tmp_path,
                                                                                      episode_kwargs):
    """A bundle whose manifest says drawer_put runs as its phases (policy/phased.py) gets them without --phases;
    --no-phases runs it as one command."""
    from policy.testing import linked_copy
    from runtime.cli import main

    phased = linked_copy(untrained_bundle, tmp_path / "phased")
    m = json.loads((phased / "manifest.json").read_text())
    (phased / "manifest.json").write_text(json.dumps({**m, "tasks": [*m["tasks"], "drawer_put"],
                                                      "instructions": [*m["instructions"], PUT],
                                                      "phased": ["drawer_put"]}))
    base = ["eval", "--policy", str(phased), "--task", "drawer_put", "--episodes", "1", "--no-collector",
            "--time-limit-factor", "0.03"]
    assert main([*base, "--out", str(tmp_path / "a")]) == 0
    assert main([*base, "--no-phases", "--out", str(tmp_path / "b")]) == 0
    assert [kw["phases"] is not None for kw in episode_kwargs] == [True, False]
    assert [kw["runs_as"] for kw in episode_kwargs] == ["drawer_put"] * 2  # its closest trained instruction's
    assert len(episode_kwargs[0]["phases"]) == 3
    summaries = [json.loads((tmp_path / d / "summary.json").read_text()) for d in "ab"]
    assert [s["settings"]["phases"] for s in summaries] == [["drawer_put"], []]
    assert summaries[0]["bundle"]["phased"] == ["drawer_put"]
    assert "(runtime/phases.py; the bundle's manifest): drawer_put" in (tmp_path / "a" / "results.md").read_text()


def test_eval_cli_refuses_heldout_without_a_holdout(untrained_bundle, tmp_path, capsys):
    from runtime.cli import main

    assert main(["eval", "--policy", str(untrained_bundle), "--suite", "heldout", "--out", str(tmp_path)]) == 2
    assert "--holdout-color" in capsys.readouterr().err


def test_ctrl_c_stops_an_evaluation_cleanly_and_keeps_its_finished_episodes(tmp_path):
    """Ctrl-C (SIGINT to the process group, as a terminal sends it) while worker processes run episodes: no
    worker traceback, exit code 130, a message saying where the results are, every finished episode kept."""
    import os
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "ev"
    cmd = [sys.executable, "-c", "import sys; from runtime.cli import main; sys.exit(main(sys.argv[1:]))", "eval",
           "--policy", "policy/bundles/demo", "--task", "pick_place", "--episodes", "40", "--no-collector",
           "--time-limit-factor", "0.03", "--latency-ms", "6", "--workers", "2", "--out", str(out)]
    # short episodes (0.03 of the time limit), many of them: the first is done in seconds, the last far later
    # Ctrl-C as in a terminal: a job started in the background of a non-interactive shell (as CI may run the
    # suite) inherits SIGINT ignored, and Python then never raises KeyboardInterrupt
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    results = out / "results.jsonl"
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and proc.poll() is None:
        if results.is_file() and results.read_text().count("\n") >= 1:
            break
        time.sleep(0.2)
    assert proc.poll() is None, proc.communicate()
    os.killpg(proc.pid, signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 130, stderr
    assert "interrupted" in stderr and str(results) in stderr and "Traceback" not in stderr, stderr
    lines = results.read_text().splitlines()
    assert 1 <= len(lines) < 40 and all(json.loads(x)["who"] == "policy" for x in lines)
    assert not (out / "summary.json").exists()


def test_eval_cli_realtime_runs_the_policy_through_the_live_stack(untrained_bundle, tmp_path, capsys):
    from runtime.cli import main

    out = tmp_path / "live"
    args = ["eval", "--policy", str(untrained_bundle), "--task", "pick_place", "--episodes", "1", "--no-collector",
            "--suite", "seen", "--suite", "paraphrase", "--time-limit-factor", "0.05", "--realtime", "--out", str(out)]
    assert main(args) == 0
    recs = [json.loads(x) for x in (out / "results.jsonl").read_text().splitlines()]
    assert sorted(r["suite"] for r in recs) == ["paraphrase", "seen"]
    for r in recs:
        assert r["mode"] == "realtime" and not r["success"] and r["end"] == "timeout", r
        live = r["realtime"]
        assert 0.0 < live["controller_on_time"] <= 1.0 and live["controller_rate_hz"] > 100.0, live
        assert set(live["exit_codes"].values()) == {0}, live  # every node of the stack ended cleanly
        assert r["sim_seconds"] >= 0.9 * 0.05 * 30  # it ran the family's time limit (30 s x 0.05) live
        assert "turn_deg" in r and r["turn_deg"] is None  # the policy node's turn, none without a turn query
        assert r["free_ticks"] == 0  # the node's free-space ticks: none for a family already at speed 1
    para = next(r for r in recs if r["suite"] == "paraphrase")
    assert para["command"] != para["instruction"]  # said in the unseen phrasing, as the lockstep eval does
    assert "Realtime" in (out / "results.md").read_text()
    assert main(args) == 0 and len((out / "results.jsonl").read_text().splitlines()) == 2  # resumed: nothing new
    # the lockstep run of the same seeds into the same directory is a different run, not "already done"
    assert main([a for a in args if a != "--realtime"]) == 0
    assert len((out / "results.jsonl").read_text().splitlines()) == 4
    capsys.readouterr()
    assert main(args + ["--latency-ms", "6"]) == 2  # the live stack's lag is its own
    assert "--latency-ms" in capsys.readouterr().err


def test_cpu_description_names_the_model_and_the_widest_vector_set():
    from runtime.machine_record import cpu_description

    info = "processor\t: 0\nmodel name\t: AMD EPYC 7B13\nflags\t\t: fpu sse4_2 avx avx2 fma\n"
    assert cpu_description(info) == "AMD EPYC 7B13 (avx2)"
    wide = info.replace("avx2 fma", "avx2 avx512f avx512bw")
    assert cpu_description(wide) == "AMD EPYC 7B13 (avx512f)"
    arm = "processor\t: 0\nFeatures\t: fp asimd evtstrm\n"
    assert cpu_description(arm).endswith("(asimd)")
    masked = "cpu family\t: 25\nmodel\t\t: 1\nmodel name\t: AMD EPYC\nflags\t\t: avx2\n"  # a VM's: no number
    assert cpu_description(masked) == "AMD EPYC (avx2; family 25 model 1)"
    zen2 = masked.replace("25", "23").replace(": 1", ": 49")
    assert cpu_description(zen2) == "AMD EPYC (avx2; family 23 model 49)"


def test_a_resumed_eval_says_when_the_machine_or_packages_changed(tmp_path, monkeypatch):
    from runtime import machine_record as env

    assert env.environment_change(tmp_path, resuming=False) == ""  # a fresh run records where it runs
    first = json.loads((tmp_path / "environment.json").read_text())
    assert first == env.library_versions()
    assert env.environment_change(tmp_path, resuming=True) == ""  # resumed here: nothing to say
    monkeypatch.setattr(env, "cpu_description", lambda cpuinfo=None: "Other CPU (avx512f)")
    said = env.environment_change(tmp_path, resuming=True)
    assert said == f"cpu: {first['cpu']} -> Other CPU (avx512f)"
    assert json.loads((tmp_path / "environment.json").read_text()) == first  # where the run started is kept
    (tmp_path / "environment.json").unlink()  # results from before the record: nothing to compare, now recorded
    assert env.environment_change(tmp_path, resuming=True) == ""
    assert json.loads((tmp_path / "environment.json").read_text())["cpu"] == "Other CPU (avx512f)"
