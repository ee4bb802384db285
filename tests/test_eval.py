"""`sudd eval`: the closed-loop episode (controller + safety + sim twins) and what it reports of an episode.

The statistics and the tables are tests/test_eval_report.py's; the grasp bookkeeping tests/test_eval_progress.py's.

The decisive check: the data collector's own actions, replayed step by step through the evaluation loop
(ControllerLoop -> SafetyFilter -> SimArm/SimGripper), solve the same seed. So the path a policy is judged on
can execute what the policy was trained to output, and a success is counted as one.
"""

import json

import numpy as np
import pytest

from runtime.eval_progress import target_name
from runtime.evaluate import run_policy_episode
from runtime.shaping import Shaping
from sim.build import build_episode
from sim.dr_config import load_dr
from sim.state import StateView
from sim.tasks import TASKS, get_task

SEED = 100_003


class Replay:
    """A bundle stand-in (the interface runtime.evaluate uses) that plays recorded actions back in order:
    call k returns actions k-1 .. k+14, so the executed rows (1 .. 8) start at action k."""

    cameras, obs_horizon, image_size, execute = ("scene", "wrist"), 2, (128, 128), slice(1, 9)
    manifest = {"horizons": {"control_hz": 10.0}}

    def __init__(self, actions: np.ndarray):
        self.actions, self.k, self.seen, self.stages = np.asarray(actions, np.float32), 0, [], []

    def embed(self, text: str) -> np.ndarray:
        return np.zeros(384, np.float32)

    def act(self, images, proprio, emb, rng=None, stage=0) -> np.ndarray:
        self.seen.append((images["scene"].shape, images["wrist"].shape, proprio.shape))
        self.stages.append(stage)
        idx = np.clip(np.arange(self.k - 1, self.k + 15), 0, len(self.actions) - 1)
        self.k += 1
        return self.actions[idx]


@pytest.fixture(scope="module")
def collected():
    from datagen.episode import DatagenConfig, run_episode

    ep = run_episode("pick_place", SEED, DatagenConfig(dr="heavy"))
    assert ep.meta["success"]
    return ep


def test_collector_actions_replayed_through_controller_and_safety_solve_the_task(collected):
    policy = Replay(collected.action)
    out = run_policy_episode(policy, "pick_place", SEED, dr="heavy")
    assert out.success and out.end == "success", out.record()
    assert out.rejected_chunks == 0 and out.chunks == policy.k > 20
    assert out.sim_seconds < len(collected.action) / 10.0 + 2.0
    assert policy.seen[0] == ((2, 128, 128, 3), (2, 128, 128, 3), (2, 16))
    # the grasp cycles the policy is given (policy.stage): none until the object is let go in the bin
    assert policy.stages[0] == 0 and policy.stages[-1] == 1 and policy.stages == sorted(policy.stages)
    assert out.grasp_cycles == 1
    assert out.target["color"] and out.target["shape"]
    assert out.held == [f"{out.target['color']} {out.target['shape']}"] and out.failure == ""
    assert out.target_end == "" and out.target_lets_go == 1  # let go once: in its bin
    (release,) = out.releases  # over the bin's middle, a few cm up, at rest
    assert np.hypot(release["dx_cm"], release["dy_cm"]) < 3.0 and 0.0 < release["up_cm"] < 15.0, release
    assert release["speed_cm_s"] < 5.0 and np.hypot(release["tcp_dx_cm"], release["tcp_dy_cm"]) < 3.0, release
    # the chunk being followed aims where the TCP is: the replay holds still over the bin to let go
    assert np.hypot(release["aim_dx_cm"] - release["tcp_dx_cm"], release["aim_dy_cm"] - release["tcp_dy_cm"]) < 1.0


class TwoModes(Replay):
    """Two chunks a call: the recorded ones and the same 4 cm to the side, in an order that swaps every call, as
    a policy whose draws fall in either of two modes (policy/coherence.py)."""

    def act(self, images, proprio, emb, rng=None, stage=0, samples=None) -> np.ndarray:
        swap = self.k % 2
        plain = super().act(images, proprio, emb, rng, stage)
        side = plain + np.array([0, 0.04] + [0] * 8, np.float32)
        assert samples == 2
        return np.stack([side, plain] if swap else [plain, side])


def test_coherence_keeps_to_the_mode_the_arm_is_in(collected):
    out = run_policy_episode(TwoModes(collected.action), "pick_place", SEED, dr="heavy", shaping=Shaping(samples=2))
    assert out.success, out.record()
    chose, changed = out.coherent_picks
    assert chose == out.chunks - 1  # every tick after the first compared, the recorded mode kept:
    assert changed == chose // 2 + chose % 2  # the second sample on every other call


def test_a_stack_release_says_how_far_off_and_how_high_over_the_block_below():
    from datagen.episode import DatagenConfig, run_episode

    ep = run_episode("stack", SEED, DatagenConfig(dr="heavy"))
    assert ep.meta["success"]
    out = run_policy_episode(Replay(ep.action), "stack", SEED, dr="heavy")
    assert out.success, out.record()
    (release,) = out.releases  # the collector lets go 1.2 cm over resting on it, centred on it
    assert np.hypot(release["dx_cm"], release["dy_cm"]) < 1.5 and 0.0 < release["over_cm"] < 2.5, release
    # let go 6 cm higher (the arm stops short of the last 6 cm), the same block reads that much over its rest
    high = ep.action.copy()
    opens = int(np.flatnonzero(np.diff(high[:, -1]) < -0.2)[-1]) + 1  # the release: the gripper channel drops
    high[opens - 8:, 2] += 0.06
    out = run_policy_episode(Replay(high), "stack", SEED, dr="heavy")
    assert abs(out.releases[0]["over_cm"] - release["over_cm"] - 6.0) < 1.0, out.record()


def test_a_drawer_release_says_how_far_outside_the_drawers_inside_it_was_let_go():
    from datagen.episode import DatagenConfig, run_episode

    ep = run_episode("drawer_stow", SEED, DatagenConfig(dr="heavy"))
    assert ep.meta["success"]
    out = run_policy_episode(Replay(ep.action), "drawer_stow", SEED, dr="heavy")
    assert out.success, out.record()
    (release,) = out.releases  # the collector lets go over the drawer's inside
    assert release["outside_cm"] == 0.0 and np.hypot(release["dx_cm"], release["dy_cm"]) < 6.0, release
    early = np.array(ep.action)  # let go half way from the grasp to the collector's let-go: short of the drawer
    grip = early[:, 9]
    grasp = int(np.argmax(grip > 0.5))
    opens = grasp + int(np.argmax(grip[grasp:] < 0.5))
    early[(grasp + opens) // 2:, 9] = grip[opens]
    out = run_policy_episode(Replay(early), "drawer_stow", SEED, dr="heavy", time_limit_factor=0.6)
    assert not out.success and out.target_end == "outside", out.record()
    assert out.releases[0]["outside_cm"] > 3.0, out.releases


@pytest.mark.parametrize("change,where", [("never_open", "held"), ("open_halfway", "outside")])
def test_a_failure_says_where_the_named_object_ended(collected, change, where):
    actions = np.array(collected.action)
    grip = actions[:, 9]
    grasp = int(np.argmax(grip > 0.5))
    release = grasp + int(np.argmax(grip[grasp:] < 0.5))
    assert 0 < grasp < release
    if change == "never_open":
        actions[grasp:, 9] = grip[grasp]
    else:
        actions[(grasp + release) // 2:, 9] = grip[release]
    out = run_policy_episode(Replay(actions), "pick_place", SEED, dr="heavy", time_limit_factor=0.6)
    assert out.failure == "target_not_placed" and out.target_end == where, out.record()
    assert out.target_lets_go == len(out.releases) == (where != "held")
    if out.releases:  # dropped on the way to the bin, far outside the bin's 13 x 15 cm
        assert np.hypot(out.releases[0]["dx_cm"], out.releases[0]["dy_cm"]) > 10.0, out.releases
    assert json.loads(json.dumps(out.record()))["target_end"] == where  # plain Python types: results.jsonl


def test_at_half_speed_the_same_chunks_take_twice_as_long_and_still_solve_the_task(collected):
    full, half = Replay(collected.action), Replay(collected.action)
    fast = run_policy_episode(full, "pick_place", SEED, dr="heavy")
    # the free-space pace off: high above the bins the arm would play at 1 (tests/test_free_pace.py)
    slow = run_policy_episode(half, "pick_place", SEED, dr="heavy", speed=0.5, shaping=Shaping(free_pace=False))
    assert fast.success and slow.success, slow.record()
    assert 1.7 < slow.sim_seconds / fast.sim_seconds < 2.3
    assert half.seen[0] == full.seen[0]  # the observations as trained: two steps, the same images and proprio
    with pytest.raises(ValueError, match="speed"):
        run_policy_episode(Replay(collected.action), "pick_place", SEED, speed=0.0)


def test_a_policy_that_holds_still_fails_at_the_time_limit(collected):
    out = run_policy_episode(Replay(collected.action[:1]), "pick_place", SEED, dr="heavy", time_limit_factor=0.05)
    assert not out.success and out.end == "timeout"
    assert 1.4 < out.sim_seconds < 1.7  # 30 s x 0.05
    assert out.held == [] and out.failure == "no_grasp"
    # it never moved, so its closest approach is where it started: the named object's distance from home
    start = build_episode("pick_place", SEED, "heavy", "fast")
    tcp = start.world.tcp_pose()[:3, 3]
    obj = StateView(start.world).position(target_name(start.instance))
    assert out.closest_cm == pytest.approx(100 * np.linalg.norm(tcp - obj), abs=1.0)


def test_a_drawer_task_reports_how_far_the_drawer_opened():
    from datagen.episode import DatagenConfig, run_episode
    from sim.tasks.drawer import OPEN_FRACTION

    seed = SEED + 1  # an open-loop replay of a contact-rich grasp can miss the bar: on SEED it does (0.34 open)
    ep = run_episode("drawer_open", seed, DatagenConfig(dr="heavy"))
    assert ep.meta["success"]
    out = run_policy_episode(Replay(ep.action), "drawer_open", seed, dr="heavy")
    assert out.success and out.drawer_end == out.drawer_max >= OPEN_FRACTION, out.record()
    still = run_policy_episode(Replay(ep.action[:1]), "drawer_open", seed, dr="heavy", time_limit_factor=0.05)
    assert not still.success and still.drawer_max < 0.1 and still.drawer_end == pytest.approx(still.drawer_max, abs=0.01)
    # no drawer in pick_place: nothing reported, rather than a 0 that reads as "never opened"
    assert run_policy_episode(Replay(ep.action[:1]), "pick_place", SEED, time_limit_factor=0.02).drawer_max is None


class SlowReplay(Replay):
    """Replay whose inference takes a different wall time on every call (0-12 ms, as a loaded CPU does)."""

    def act(self, images, proprio, emb, rng=None, stage=0) -> np.ndarray:
        import time

        time.sleep(float(np.random.default_rng().uniform(0.0, 0.012)))
        return super().act(images, proprio, emb, rng, stage)


def _tcp_trace(collected, **kw) -> np.ndarray:
    trace = []
    run_policy_episode(SlowReplay(collected.action), "pick_place", SEED, dr="heavy", time_limit_factor=0.1,
                       observer=lambda world, inst: trace.append(world.tcp_pose()[:3, 3].copy()), **kw)
    return np.asarray(trace)


def test_a_fixed_latency_makes_an_episode_repeatable_and_the_latency_moves_it(collected):
    a, b = _tcp_trace(collected, latency_s=0.006), _tcp_trace(collected, latency_s=0.006)
    assert len(a) > 20 and np.array_equal(a, b)  # bit for bit, whatever the wall time of each inference
    # 25 controller cycles late: the chunk's time stamps absorb most of it (latency compensation), not all
    late = _tcp_trace(collected, latency_s=0.05)
    assert len(late) == len(a) and not np.array_equal(late, a)


def test_a_filmstrip_shows_the_episode_and_changes_nothing(collected, tmp_path):
    from PIL import Image

    from runtime.eval_filmstrip import Filmstrip

    strip = Filmstrip(every_s=1.0, size=(64, 48))
    trace = []

    def both(world, inst):
        strip(world, inst)
        trace.append(world.tcp_pose()[:3, 3].copy())

    run_policy_episode(Replay(collected.action), "pick_place", SEED, dr="heavy", time_limit_factor=0.1,
                       latency_s=0.006, observer=both)
    plain = []
    run_policy_episode(Replay(collected.action), "pick_place", SEED, dr="heavy", time_limit_factor=0.1,
                       latency_s=0.006, observer=lambda world, inst: plain.append(world.tcp_pose()[:3, 3].copy()))
    assert np.array_equal(np.asarray(trace), np.asarray(plain))  # rendering read the sim, never moved it
    png = strip.save(tmp_path / "s.png", "seed 100003")
    strip.close()
    times = [float(c.split(" s")[0]) for c, _ in strip.frames]
    assert times[:3] == [0.0, 1.0, 2.0] and len(times) == 4 and 2.5 < times[3] <= 3.0  # every 1 s, then the end
    first, last = strip.frames[0][1], strip.frames[-1][1]
    assert first.shape == (96, 64, 3) and np.abs(first.astype(int) - last).mean() > 1  # scene over wrist; it moved
    with Image.open(png) as im:
        assert im.size[0] == 4 * (64 + 4) + 4


def test_a_filmstrip_keeps_one_frame_per_interval_however_its_calls_fall(monkeypatch):
    from types import SimpleNamespace

    from runtime.eval_filmstrip import Filmstrip

    strip, grabbed = Filmstrip(every_s=2.0), []
    monkeypatch.setattr(strip, "_grab", lambda world: grabbed.append(world.time))
    for t in (0.0, 0.1, 1.9, 5.3, 5.4, 6.0, 6.1):
        strip(SimpleNamespace(time=t), None)
    assert grabbed == [0.0, 5.3, 6.0]  # after a gap, the next frame waits for the next multiple of 2 s


def test_paraphrases_are_phrasings_the_data_never_used():
    dr = load_dr("heavy")
    for name in TASKS:
        family = get_task(name)
        inst = family.sample(np.random.default_rng(5), dr)
        fields = family.fields(inst)
        seen = {t.format(**fields) for t in family.templates}
        assert inst.instruction in seen  # fields() recovers what sample() filled in
        for k in range(5):
            p = family.paraphrase(inst, np.random.default_rng(k))
            assert p not in seen and all(v in p for v in fields.values())
