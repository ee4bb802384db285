"""Which of the runtime's steps between the denoiser and the controller run (runtime/chunk_shaper.py), and how many
chunks are sampled per tick: the settings `sudd eval`, `sudd run` and the policy node share.

Plain dataclass, no imports of ours: the launcher builds node configs from it without loading the model or the sim.
"""

from __future__ import annotations

from dataclasses import dataclass, fields


@dataclass(frozen=True)
class Shaping:
    """Each step True by default (False to measure what it buys on the same seeds); `samples` per tick."""
    served_pause: bool = True  # runtime/served_pause.py
    finger_wait: bool = True  # runtime/finger_wait.py
    grasp_steer: bool = True  # runtime/grasp_steer.py
    release_guard: bool = True  # runtime/release_guard.py
    handle_height: bool = True  # runtime/handle_height.py
    free_pace: bool = True  # runtime/free_pace.py
    empty_close: bool = True  # runtime/empty_close.py
    samples: int = 1  # policy/coherence.py


def shaping_of(settings: dict) -> Shaping:
    """The Shaping a settings mapping names (`sudd eval`'s, a node config's as a dict); steps it omits run."""
    return Shaping(**{f.name: settings[f.name] for f in fields(Shaping) if f.name in settings})
