"""`sudd compare`: two bundles' `sudd eval` results on the same seeds, paired: what one gained and lost.

Why paired: each seed is one scene, and most of an episode's outcome is the scene's (a block at the edge, a
drawer at the cabinet's yaw extreme), so two bundles' rates over the same 40 seeds differ far less by chance
than two independent samples of 40 would; the seeds where exactly one of them succeeds carry the whole
comparison. The test is the exact McNemar test (a two-sided binomial test on those seeds at p = 1/2), which
makes no normal approximation, so it holds for the handful of discordant seeds an evaluation here has.

A bundle's results may lie in several eval directories (seen seeds in one, fresh seeds in another): each side
takes a list, and a seed recorded twice with two outcomes is an error, not a silent choice.
"""

from __future__ import annotations

import argparse
import json
from math import comb
from pathlib import Path

EPILOG = """\
Reads OUT/results.jsonl of each `sudd eval --out OUT` (the policy's episodes; the collector's are ignored) and
pairs the two sides' episodes by (suite, task, seed). Seeds only one side ran are counted, never compared.

examples:
  sudd compare --baseline out/eval_old --candidate out/eval_new
  sudd compare --baseline out/eval_old_seen --baseline out/eval_old_fresh \\
               --candidate out/eval_new_seen --candidate out/eval_new_fresh --seeds
  sudd compare --baseline out/eval_old --candidate out/eval_new --json
"""

Key = tuple[str, str, int]  # (suite, task, seed)


def mcnemar_exact(gained: int, lost: int) -> float:
    """Two-sided exact McNemar p: the chance of a split of the discordant seeds at least this uneven when
    either side is as likely to win each of them; 1.0 when there are none."""
    if gained < 0 or lost < 0:
        raise ValueError(f"gained {gained}, lost {lost}: expected counts >= 0")
    n = gained + lost
    if n == 0:
        return 1.0
    tail = sum(comb(n, i) for i in range(min(gained, lost) + 1)) / 2 ** n
    return min(1.0, 2.0 * tail)


def load_outcomes(dirs: list[Path]) -> dict[Key, bool]:
    """The policy's success per (suite, task, seed) over the eval directories `dirs`."""
    from runtime.eval_cli import read_results

    out: dict[Key, bool] = {}
    where: dict[Key, Path] = {}
    for d in dirs:
        path = Path(d) / "results.jsonl"
        if not path.is_file():
            raise ValueError(f"{d}: no results.jsonl (expected the --out directory of a `sudd eval`)")
        # as `sudd eval` reads it: a line cut by a kill is skipped (that episode runs again on a resume)
        for n, rec in enumerate(read_results(path), 1):
            try:
                if rec.get("who", "policy") != "policy":
                    continue
                key, ok = (str(rec["suite"]), str(rec["task"]), int(rec["seed"])), bool(rec["success"])
            except (AttributeError, KeyError, TypeError, ValueError) as exc:
                raise ValueError(f"{path}:{n}: not an eval record ({exc}); expected a line of `sudd eval`'s "
                                 "results.jsonl with suite, task, seed and success") from None
            if key in out and out[key] != ok:
                raise ValueError(f"{key[1]} seed {key[2]} ({key[0]}) is in {where[key]} and {d} with different "
                                 "outcomes; give each seed once per side")
            out[key], where[key] = ok, Path(d)
    if not out:
        raise ValueError(f"{', '.join(map(str, dirs))}: no policy episodes to compare")
    return out


def compare(baseline: dict[Key, bool], candidate: dict[Key, bool]) -> list[dict]:
    """One row per (suite, task) either side ran: successes on the shared seeds, seeds gained and lost by the
    candidate, the exact McNemar p, and how many seeds only one side has."""
    groups = sorted({k[:2] for k in baseline} | {k[:2] for k in candidate})
    rows = []
    for suite, task in groups:
        b = {k[2]: v for k, v in baseline.items() if k[:2] == (suite, task)}
        c = {k[2]: v for k, v in candidate.items() if k[:2] == (suite, task)}
        shared = sorted(set(b) & set(c))
        gained = [s for s in shared if c[s] and not b[s]]
        lost = [s for s in shared if b[s] and not c[s]]
        rows.append({"suite": suite, "task": task, "n": len(shared),
                     "baseline": sum(b[s] for s in shared), "candidate": sum(c[s] for s in shared),
                     "gained": gained, "lost": lost, "p": mcnemar_exact(len(gained), len(lost)),
                     "baseline_only": len(set(b) - set(c)), "candidate_only": len(set(c) - set(b))})
    return rows


def markdown(rows: list[dict], seeds: bool = False) -> str:
    lines = ["| suite | task | shared seeds | baseline | candidate | gained | lost | exact McNemar p | "
             "seeds on one side only |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        one_side = f"{r['baseline_only']} baseline, {r['candidate_only']} candidate"
        lines.append(f"| {r['suite']} | {r['task']} | {r['n']} | {r['baseline']} | {r['candidate']} | "
                     f"{len(r['gained'])} | {len(r['lost'])} | {r['p']:.3f} | {one_side} |")
    if len(rows) > 1:  # the families pooled: a paired test over all shared episodes
        g, lo = sum(len(r["gained"]) for r in rows), sum(len(r["lost"]) for r in rows)
        lines.append(f"| all | all | {sum(r['n'] for r in rows)} | {sum(r['baseline'] for r in rows)} | "
                     f"{sum(r['candidate'] for r in rows)} | {g} | {lo} | {mcnemar_exact(g, lo):.3f} | |")
    if seeds:
        lines.append("")
        for r in rows:
            lines.append(f"{r['suite']} {r['task']}: gained {r['gained'] or '-'}; lost {r['lost'] or '-'}")
    return "\n".join(lines)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("compare", help="two bundles' eval results on the same seeds, paired (gained, lost, exact "
                                       "McNemar p)",
                       description="Compare a candidate bundle's `sudd eval` results with a baseline's, seed by "
                                   "seed: successes on the seeds both ran, the seeds the candidate gained and "
                                   "lost, and the exact McNemar p (two-sided) per suite and task family.",
                       epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--baseline", action="append", required=True, type=Path, metavar="EVAL_DIR",
                   help="a `sudd eval --out` directory of the baseline bundle (repeatable)")
    p.add_argument("--candidate", action="append", required=True, type=Path, metavar="EVAL_DIR",
                   help="a `sudd eval --out` directory of the candidate bundle (repeatable)")
    p.add_argument("--seeds", action="store_true", help="also list the seeds gained and lost")
    p.add_argument("--json", action="store_true", help="print the rows as JSON")
    p.set_defaults(func=_compare)


def _compare(args) -> int:
    rows = compare(load_outcomes(args.baseline), load_outcomes(args.candidate))
    if not any(r["n"] for r in rows):
        raise ValueError("the two sides share no (suite, task, seed): run `sudd eval` on the same seeds and "
                         "tasks for both (the same --seed-offset/--episodes or --seeds)")
    print(json.dumps(rows, indent=2) if args.json else markdown(rows, seeds=args.seeds))
    return 0
