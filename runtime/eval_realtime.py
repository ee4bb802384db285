"""`sudd eval --realtime`: each policy episode through the stack `sudd run --sim` starts, in real time.

Why beside the lockstep eval (runtime.evaluate): lockstep runs one controller cycle per physics step and lets
a fixed or measured inference lag pass, so it measures the policy, repeatably. What a user deploys is
processes on one host's cores: the robot node's 500 Hz controller next to the physics and the renderer, the
policy node inferring on camera frames that travel over Zenoh. Late control cycles there once cost
drawer_open most of its episodes in protective stops that lockstep never showed (ControllerConfig's
`catch_up_periods`). This runs the same seeds through that stack, so the two figures can be compared.

An episode: the sim stack (runtime.launch.sim_stack) for the task and seed, the command said once ready
(the episode's instruction, or its paraphrase in the paraphrase suite), then watched until the robot node
reports task success, the sim's safety system stops the arm (a protective stop ends it, as in lockstep), or
the family's time limit (times --time-limit-factor) passes. Sequential: episodes running side by side would
take each other's CPU, which is what this measures. The collector's episodes are the lockstep eval's.
"""

from __future__ import annotations

import time

from runtime.controller import ControllerConfig
from runtime.shaping import shaping_of

_ENDING = ("task_success", "sim_protective_stop")


def run_realtime_episode(job: dict, settings: dict, controller: ControllerConfig) -> dict:
    """One policy episode of `sudd eval --realtime` (see the module docstring): a record for eval_report."""
    from runtime import bus as B
    from runtime.launch import Launcher, sim_stack
    from runtime.evaluate import episode_command, suite_holdout
    from sim.tasks import get_task

    task, seed = job["task"], int(job["seed"])
    h = settings["holdout"]
    holdout = suite_holdout(job["suite"], h)
    command = ""
    if job["suite"] == "paraphrase":  # the same phrasing the lockstep eval gives this seed
        command = episode_command(task, seed, settings["dr"], holdout, paraphrase=True)
    limit_s = get_task(task).max_seconds * settings["time_limit_factor"]
    specs = sim_stack(settings["bundle"], task=task, seed=seed, dr=settings["dr"], command=command,
                      replan_every=settings["replan_every"], speed=settings["speed"],
                      goal_query=settings["goal_query"], phases=task in settings["phases"],
                      shaping=shaping_of(settings),
                      controller=controller, holdout_colors=holdout.colors, holdout_shapes=holdout.shapes,
                      holdout_split=holdout.split)
    seen: set[str] = set()

    def on_event(msg) -> None:
        if msg.kind in _ENDING:
            seen.add(msg.kind)

    la = Launcher(specs, hub="tcp/127.0.0.1:0")
    with la:
        info = la.wait_ready()
        text = command or info["robot"].get("instruction") or ""
        la.bus.subscribe(B.SAFETY_EVENT, on_event)
        t0 = time.monotonic()
        la.say(text, "eval")
        la.monitor(duration_s=limit_s, until=lambda: bool(seen))
    rob, pol = la.reports.get("robot", {}), la.reports.get("policy", {})
    stops = rob.get("protective_stops") or []
    # as in lockstep, a protective stop ends the episode: a drawer the impact pushed open after it is no success
    success = bool(rob.get("task_success")) and (not stops or rob.get("success_after_s", 0.0) < stops[0]["after_s"])
    if success:
        end = "success"
    elif stops or "sim_protective_stop" in seen:
        end = "protective_stop"
    else:
        end = "timeout"
    first_stop = stops[0] if stops else {}
    cs = rob.get("controller_summary", {})
    speed = first_stop.get("tcp_speed_m_s")
    infer = pol.get("inference_ms") or {}  # none without an accepted command
    return {"command": text, "instruction": info["robot"].get("instruction"), "success": success,
            "sim_seconds": round(rob["success_after_s"], 3) if success and rob.get("success_after_s") else
            round(time.monotonic() - t0, 3), "end": end, "stop_reason": first_stop.get("reason", ""),
            "stop_speed_cm_s": None if speed is None else round(100.0 * speed, 1),
            "goal_point": pol.get("goal_point"), "turn_deg": pol.get("turn_deg"), "chunks": pol.get("chunks"),
            "free_ticks": pol.get("free_ticks"),
            "inference_ms": infer if "p50" in infer else None, "failure": "",
            "realtime": {"controller_on_time": cs.get("on_time"), "controller_rate_hz": cs.get("rate_hz"),
                         "track_err_p50_mrad": cs.get("track_err_p50_mrad"),
                         "obs_to_accepted_ms": (rob.get("latency_ms") or {}).get("accepted"),
                         "exit_codes": la.exit_codes}}


__all__ = ["run_realtime_episode"]
