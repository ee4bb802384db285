"""A phased family's episodes cut into their phases, each kept as an episode of the skill that phase runs.

Why: drawer_put runs as its phases (runtime/phases.py), and its last phase is drawer_close's skill, "close the
drawer". drawer_close's data starts at home with an empty drawer; inside drawer_put the skill starts where the
object was let go, above the open drawer, with the object in it. Sent home first, the skill grasped the object
again or pushed it out (policy/EXPERIMENTS.md, "Back to the start before closing the drawer"). The collector's
drawer_put episodes already show that skill from where the runtime hands it over, so their closing cycle is
drawer_close data the policy never saw: cut at the step where the runtime switches phase (the grasp cycles
completed, policy.stage, counted as the runtime counts them) and given the phase's own text.

A cut episode keeps its source's seed, so its (family, seed) does not rebuild its scene: meta["phase_of"] names
the episode it came from (task, seed, phase, the steps it spans, the source instruction), and code that
rebuilds scenes from a dataset's seeds (datagen.views.measure_offsets) leaves such episodes out.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from datagen.schema import EpisodeData, episode_success
from datagen.store import Dataset, ShardWriter, StoreError, episode_key
from policy.phased import OWN_PHASE_TEXT, PHASED, own_phase_text
from policy.stage import GRIPPER_COLUMN, commands_in_effect, cycles_per_step

MIN_STEPS = 8  # a phase shorter than this (0.8 s) is not a demonstration of its skill
# Steps a phase under a text of its own (policy.phased.OWN_PHASE_TEXT) runs on past its switch. Why: a window's
# "now" stops Tp - Ta + 1 steps before an episode's end (policy.data), so a cut that ends at the object's release
# never shows the frames over the drawer as "now", and no other episode carries that text: the first such bundle
# held the object over the drawer and never let go (policy/EXPERIMENTS.md). 16 = the prediction horizon.
OWN_TEXT_TAIL = 16


@dataclass
class CutReport:
    written: dict = field(default_factory=dict)  # family -> episodes written
    skipped: dict = field(default_factory=dict)  # reason -> count
    kept_before: int = 0  # already in OUT (a continued run)

    def skip(self, reason: str) -> None:
        self.skipped[reason] = self.skipped.get(reason, 0) + 1


def cuttable_phases(family: str) -> list[int]:
    """Every phase of `family` with a text: the skill phases and those with a text of their own."""
    return sorted({*skill_phases(family), *OWN_PHASE_TEXT.get(family, {})})


def skill_phases(family: str) -> list[int]:
    """The phases of `family` that run another family's skill under their own text (not the command itself)."""
    if family not in PHASED:
        raise ValueError(f"{family!r} has no phases; families with phases: {', '.join(sorted(PHASED))}")
    return [k for k, (text, _) in enumerate(PHASED[family]) if text is not None]


def phase_span(action: np.ndarray, proprio: np.ndarray, phase: int, last: bool) -> tuple[int, int] | None:
    """The steps [start, stop) in which phase `phase` runs, as the runtime switches: from the first step at
    which `phase` grasp cycles are complete to the first at which one more is (the last phase: to the end).
    None when the episode never reaches the phase."""
    cycles = cycles_per_step(commands_in_effect(action), proprio[:, GRIPPER_COLUMN])
    reached = np.flatnonzero(cycles >= phase)
    if not len(reached):
        return None
    start = int(reached[0])
    beyond = np.flatnonzero(cycles > phase)
    stop = len(cycles) if last or not len(beyond) else int(beyond[0])
    return start, stop


def cut_episode(ep: EpisodeData, phase: int) -> EpisodeData | str:
    """Episode `ep` (of a phased family) cut to its phase `phase`, labelled with that phase's text and family
    (a phase of the family itself: its own text, policy.phased.OWN_PHASE_TEXT, with the episode's object);
    or the reason it cannot be (a string)."""
    family = ep.meta["task"]
    table = PHASED[family]
    text, skill = table[phase]
    own = text is None
    if own:
        text = own_phase_text(family, phase, ep.meta["instruction"])
        if text is None:
            return f"phase {phase}: no object named in the instruction"
    span = phase_span(ep.action, ep.proprio, phase, last=phase == len(table) - 1)
    if span is None:
        return f"phase {phase} never reached"
    a, b = span
    if own:
        b = min(b + OWN_TEXT_TAIL, len(ep))
    # a re-grasp (of a slipping handle, say) counts a cycle early: the phase would begin inside another subtask
    labels = list(ep.meta.get("subtasks") or [])
    if text in labels:
        first = np.flatnonzero(ep.subtask == labels.index(text))
        if not len(first) or abs(int(first[0]) - a) > 20:
            return "grasp cycles and subtask labels disagree"
    if b - a < MIN_STEPS:
        return f"phase {phase} shorter than {MIN_STEPS} steps"
    meta = dict(ep.meta, task=skill, instruction=text, phase_of={
        "task": family, "seed": int(ep.meta["seed"]), "phase": phase, "start": a, "stop": b,
        "instruction": ep.meta["instruction"]})
    # the releases inside the cut, counted from its start (datagen/release_offsets.py)
    releases = [dict(r, step=int(r["step"]) - a) for r in ep.meta.get("release_offsets") or [] if a <= r["step"] < b]
    meta.pop("release_offsets", None)
    if releases:
        meta["release_offsets"] = releases
    return EpisodeData(images={c: v[a:b] for c, v in ep.images.items()}, proprio=ep.proprio[a:b],
                       action=ep.action[a:b], subtask=ep.subtask[a:b], time=ep.time[a:b] - ep.time[a], meta=meta)


def cut_phases(source: str | Path, out: str | Path, phases: dict[str, list[int]] | None = None,
               progress=None) -> CutReport:
    """Write into OUT/shards/phases.zarr the phases (`phases`: family -> phase indexes; default every phase that
    runs another skill) of every verified episode of SOURCE's phased families. Re-running continues."""
    src = Dataset(source)
    if Path(out).resolve() == src.root.resolve():
        raise StoreError("cut into a new directory, not into the dataset being read")
    phases = phases if phases is not None else {f: skill_phases(f) for f in PHASED}
    report = CutReport()
    with ShardWriter(out, "phases") as writer:
        report.kept_before = len(writer.keys)
        for i in range(len(src)):
            meta = src.meta(i)
            family = meta["task"]
            if family in phases and not episode_success(meta):
                report.skip("not verified")
            elif family in phases:
                ep = src.episode(i)
                for k in phases[family]:
                    cut = cut_episode(ep, k)
                    if isinstance(cut, str):
                        report.skip(cut)
                    elif episode_key(cut.meta) not in writer.keys:
                        writer.append(cut)
                        report.written[cut.meta["task"]] = report.written.get(cut.meta["task"], 0) + 1
            if progress is not None:
                progress()
    return report


def parse_phase_args(items: list[str] | None) -> dict[str, list[int]] | None:
    """`--phase FAMILY:K` arguments -> {family: [K, ...]} (None: the default, every skill phase)."""
    if not items:
        return None
    out: dict[str, list[int]] = {}
    for item in items:
        family, _, k = item.partition(":")
        if family not in PHASED:
            raise ValueError(f"--phase {item!r}: {family!r} has no phases; families with phases: "
                             f"{', '.join(sorted(PHASED))}")
        n = len(PHASED[family])
        if not k.isdigit() or int(k) >= n:
            raise ValueError(f"--phase {item!r}: expected FAMILY:K with K in 0..{n - 1}")
        if PHASED[family][int(k)][0] is None and int(k) not in OWN_PHASE_TEXT.get(family, {}):
            raise ValueError(f"--phase {item!r}: phase {k} of {family} is the command itself, with no text of its "
                             f"own; phases with a text: {cuttable_phases(family)}")
        out.setdefault(family, []).append(int(k))
    return out
