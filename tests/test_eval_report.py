"""runtime.eval_report: Wilson intervals, the per-family summary, the results and failure tables, the chart."""

import numpy as np
import pytest

from runtime.eval_report import failure_table, markdown_table, plot, summarise, wilson


def test_wilson_interval():
    assert wilson(0, 0) == (0.0, 1.0)
    lo, hi = wilson(0, 10)
    assert lo == pytest.approx(0.0) and hi == pytest.approx(0.2775, abs=1e-4)
    lo, hi = wilson(10, 10)
    assert lo == pytest.approx(0.7225, abs=1e-4) and hi == pytest.approx(1.0)
    lo, hi = wilson(5, 10)
    assert lo == pytest.approx(0.2366, abs=1e-4) and hi == pytest.approx(0.7634, abs=1e-4)
    assert wilson(80, 100)[1] - wilson(80, 100)[0] < wilson(8, 10)[1] - wilson(8, 10)[0]


def test_summary_table_and_chart(tmp_path):
    recs = [{"suite": "seen", "task": "pick_place", "who": "policy", "success": s, "sim_seconds": 9.0,
             "inference_ms": {"p50": 20.0}} for s in (True, True, True, False)]
    recs += [{"suite": "seen", "task": "pick_place", "who": "collector", "success": s, "sim_seconds": 8.0}
             for s in (True, False, False, False)]
    recs[3].update(failure="wrong_object", end="protective_stop", closest_cm=1.0,  # held: not a no_grasp
                   stop_speed_cm_s=17.5, stop_fingers_closed=True)
    recs += [{"suite": "seen", "task": "pick_place", "who": "policy", "success": False, "sim_seconds": 30.0,
              "failure": "target_not_placed", "end": "timeout", "target_end": e, "releases": let_go}
             for e, let_go in (("outside", [{"dx_cm": 30.0, "dy_cm": 0.0},
                                            {"dx_cm": 6.0, "dy_cm": 8.0, "aim_dx_cm": 3.0, "aim_dy_cm": 4.0,
                                             "tcp_dx_cm": 6.0, "tcp_dy_cm": 5.0}]),
                               ("held", []), ("outside", [{"dx_cm": 0.0, "dy_cm": -20.0, "aim_dx_cm": None}]))]
    recs[0]["releases"] = [{"dx_cm": 1.0, "dy_cm": 0.0, "up_cm": 4.0}]
    recs += [{"suite": "paraphrase", "task": "pick_place", "who": "policy", "success": False, "sim_seconds": 30.0,
              "failure": "no_grasp", "end": "timeout", "closest_cm": c, "closes": k}
             for c, k in ((12.5, []), (3.0, [{"yaw_off_deg": y} for y in (-80.0, 88.0, 5.0, None)]),
                          (7.25, [{"yaw_off_deg": 85.0}]))]
    # drawer_put: two failures opened the drawer (one to the 80 % that counts), one never did; a success did
    recs += [{"suite": "seen", "task": "drawer_put", "who": "policy", "success": s, "sim_seconds": 60.0,
              "failure": "" if s else "no_grasp", "end": "success" if s else "timeout", "drawer_max": f}
             for s, f in ((False, 0.85), (False, 0.79), (False, 0.02), (True, 1.0))]
    rows = summarise(recs)
    assert [(r["suite"], r["task"], r["who"], r["successes"], r["n"]) for r in rows] == [
        ("seen", "drawer_put", "policy", 1, 4), ("seen", "pick_place", "collector", 1, 4),
        ("seen", "pick_place", "policy", 3, 7), ("paraphrase", "pick_place", "policy", 0, 3)]
    assert rows[0]["failed_drawer_opened"] == 1 and rows[2]["failed_drawer_opened"] is None
    assert failure_table(rows[:1]).splitlines()[2].endswith("| - | - | 1 |")
    rows = [r for r in rows if r["task"] == "pick_place"]
    table = markdown_table(rows)
    assert "| seen | pick_place | 3/7 = 43% [16, 75] | 1/4 = 25% [5, 70] | 9.0 s |" in table
    assert "| paraphrase | pick_place | 0/3 = 0% [0, 56] | - | - |" in table
    why = failure_table(rows).splitlines()
    assert why[0] == ("| suite | task | failed | no_grasp | wrong_object | target_not_placed | ended: protective_stop "
                      "| ended: timeout | force stops: TCP speed at the stop (median); how many with the fingers closed "
                      "| no_grasp: median closest approach | no_grasp: yaw off at a close (median) "
                      "| target_not_placed: the object ended "
                      "| target_not_placed: let go off the goal's centre (median; where the chunk aimed the TCP; "
                      "how far off the TCP the fingers held it; stack: how high over resting on the other; "
                      "drawer: how far outside its inside) "
                      "| drawer opened (>= 80% of its travel) |")
    # the last let-go counts: 10 cm (after a drop at 30) and 20 cm; only the first recorded an aim (5 cm) and
    # where the TCP was
    assert why[2:] == ["| seen | pick_place | 4 | 0 | 1 | 3 | 1 | 3 | 17.5 cm/s; 1 closed | - | - | held 1, outside 2 "
                       "| 15.0 cm (aimed 5.0 cm; held 3.0 cm off) | - |",
                       "| paraphrase | pick_place | 3 | 3 | 0 | 0 | 0 | 3 | - | 7.2 cm | 85 deg | - | - | - |"]
    assert rows[1]["release_off_cm"] == {"success": 1.0, "target_not_placed": 15.0}
    assert rows[1]["release_aim_off_cm"] == {"success": None, "target_not_placed": 5.0}
    # the one let-go that recorded its TCP: 3 cm off it in the fingers (the other recorded none)
    assert rows[1]["release_in_hand_cm"] == {"success": None, "target_not_placed": 3.0}
    assert rows[1]["release_over_cm"] == {"success": None, "target_not_placed": None}  # bins: no block below
    stack = [{"suite": "seen", "task": "stack", "who": "policy", "success": False, "sim_seconds": 30.0,
              "failure": "target_not_placed", "end": "timeout", "target_end": "released",
              "releases": [{"dx_cm": 0.0, "dy_cm": d, "over_cm": h}]} for d, h in ((2.0, 3.0), (3.0, 5.0), (4.0, 1.0))]
    (row,) = summarise(stack)
    assert row["release_over_cm"]["target_not_placed"] == 3.0
    assert "| released 3 | 3.0 cm, 3.0 cm over its rest | - |" in failure_table([row])
    stow = [{"suite": "seen", "task": "drawer_stow", "who": "policy", "success": False, "sim_seconds": 30.0,
             "failure": "target_not_placed", "end": "timeout", "target_end": "outside", "drawer_max": 0.95,
             "releases": [{"dx_cm": 0.0, "dy_cm": d, "outside_cm": o}]} for d, o in ((9.0, 4.0), (8.0, 2.0))]
    (row,) = summarise(stow)
    assert row["release_outside_cm"] == {"success": None, "target_not_placed": 3.0}
    assert "| outside 2 | 8.5 cm, 3.0 cm outside the drawer | 2 |" in failure_table([row])
    assert failure_table([r for r in rows if r["who"] == "collector"]) == ""
    png = plot(rows, tmp_path / "chart.png")
    from PIL import Image

    with Image.open(png) as im:
        assert im.size[0] > 300 and len(np.unique(np.asarray(im.convert("L")))) > 5
