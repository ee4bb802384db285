"""`sudd compare`: two bundles' eval results paired seed by seed, the exact McNemar p, bad input refused."""

import json

import pytest

from runtime.eval_compare import compare, load_outcomes, mcnemar_exact


def _write(d, rows):
    d.mkdir(parents=True, exist_ok=True)
    lines = [json.dumps({"suite": s, "task": t, "seed": seed, "who": who, "success": ok})
             for s, t, seed, ok, who in rows]
    (d / "results.jsonl").write_text("\n".join(lines) + "\n")
    return d


def test_mcnemar_exact_matches_the_binomial_tails():
    assert mcnemar_exact(0, 0) == 1.0
    assert mcnemar_exact(0, 5) == pytest.approx(2 / 32)  # all five discordant seeds one way
    assert mcnemar_exact(5, 0) == mcnemar_exact(0, 5)
    assert mcnemar_exact(7, 16) == pytest.approx(0.0931, abs=1e-4)
    assert mcnemar_exact(3, 3) == 1.0
    with pytest.raises(ValueError, match="expected counts"):
        mcnemar_exact(-1, 2)


def test_pairs_seeds_across_directories_and_ignores_the_collector(tmp_path):
    a1 = _write(tmp_path / "a1", [("seen", "stack", 1, True, "policy"), ("seen", "stack", 2, True, "policy"),
                                  ("seen", "stack", 1, False, "collector")])
    a2 = _write(tmp_path / "a2", [("seen", "stack", 3, False, "policy"), ("seen", "stack", 9, True, "policy")])
    b = _write(tmp_path / "b", [("seen", "stack", 1, False, "policy"), ("seen", "stack", 2, True, "policy"),
                                ("seen", "stack", 3, True, "policy"), ("seen", "drawer_open", 1, True, "policy")])
    rows = compare(load_outcomes([a1, a2]), load_outcomes([b]))
    stack = next(r for r in rows if r["task"] == "stack")
    assert (stack["n"], stack["baseline"], stack["candidate"]) == (3, 2, 2)
    assert stack["gained"] == [3] and stack["lost"] == [1]
    assert stack["baseline_only"] == 1 and stack["candidate_only"] == 0  # seed 9: never compared
    other = next(r for r in rows if r["task"] == "drawer_open")
    assert other["n"] == 0 and other["candidate_only"] == 1


def test_a_seed_with_two_outcomes_on_one_side_is_refused(tmp_path):
    a1 = _write(tmp_path / "a1", [("seen", "stack", 1, True, "policy")])
    a2 = _write(tmp_path / "a2", [("seen", "stack", 1, False, "policy")])
    with pytest.raises(ValueError, match="different outcomes"):
        load_outcomes([a1, a2])


def test_bad_directories_and_lines_are_refused_with_the_reason(tmp_path):
    with pytest.raises(ValueError, match="no results.jsonl"):
        load_outcomes([tmp_path / "missing"])
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "results.jsonl").write_text('{"suite": "seen", "task": "stack"}\n')
    with pytest.raises(ValueError, match=r"results.jsonl:1: not an eval record"):
        load_outcomes([bad])
    only = _write(tmp_path / "only", [("seen", "stack", 1, True, "collector")])
    with pytest.raises(ValueError, match="no policy episodes"):
        load_outcomes([only])


def test_cli_prints_the_table_and_refuses_sides_without_shared_seeds(tmp_path, capsys):
    from runtime.cli import main

    a = _write(tmp_path / "a", [("seen", "stack", s, s % 2 == 0, "policy") for s in range(10)])
    b = _write(tmp_path / "b", [("seen", "stack", s, True, "policy") for s in range(10)])
    assert main(["compare", "--baseline", str(a), "--candidate", str(b), "--seeds"]) == 0
    out = capsys.readouterr().out
    assert "| seen | stack | 10 | 5 | 10 | 5 | 0 | 0.062 |" in out
    assert "gained [1, 3, 5, 7, 9]" in out
    assert main(["compare", "--baseline", str(a), "--candidate", str(b), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)[0]["gained"] == [1, 3, 5, 7, 9]
    c = _write(tmp_path / "c", [("seen", "stack", 100, True, "policy")])
    assert main(["compare", "--baseline", str(a), "--candidate", str(c)]) == 2
    assert "share no (suite, task, seed)" in capsys.readouterr().err
