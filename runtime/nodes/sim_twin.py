"""What the robot node does only with the sim twins: its own cameras' sensor DR, and a protective stop's cause.

Why here: the robot node drives real hardware and its sim twin through one path; these are the two places the
twin knows more than the hardware (the episode's sensor parameters, the contact that tripped the stop) and
says so, kept out of that path.
"""

from __future__ import annotations

import numpy as np


def frame_noises(episode, seed: int, cameras) -> dict:
    """camera name -> (img -> img) with the episode's sensor DR (gain, pixel noise: the parameters its recorded
    frames and sim_render's have for the seed, drawn once), one noise stream per camera."""
    from sim.randomize import corrupt_image, episode_sensor_params

    sensor = episode_sensor_params(episode)

    def noise(rng):
        return lambda img: corrupt_image(img, sensor, rng)

    return {name: noise(np.random.default_rng([seed, 13, i])) for i, name in enumerate(cameras)}


def note_sim_stop(rig, seen: str | None, after_s: float, report: dict, event) -> str | None:
    """Record a new protective stop of the sim twin with its cause (which contact, how hard, how fast: what
    an operator needs, and what a real UR tells only on its pendant) once; returns the stop now seen."""
    if not rig.protective_stopped:
        return None
    reason = rig.stop_reason
    if not reason or reason == seen:
        return seen
    report["protective_stops"].append({"after_s": round(after_s, 3), "reason": reason,
                                       "tcp_speed_m_s": rig.stop_tcp_speed})
    if event is not None:
        event("sim_protective_stop", "error", f"the sim's safety system stopped the arm: {reason}", after_s=after_s)
    return reason


__all__ = ["frame_noises", "note_sim_stop"]
