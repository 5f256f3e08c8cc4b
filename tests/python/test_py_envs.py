"""The Python package's RL environments against their own frameworks' checkers (PettingZoo's
parallel_api_test and parallel_seed_test, Gymnasium's check_env), plus what the checkers
cannot see: vector autoreset semantics, seeded replay bit for bit, reward formulas, crashes,
custom reward functions and bad arguments. Episodes are short (max_steps 3 to 120) so that the
file stays under a minute on a debug build."""
import math
import warnings

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode
from pettingzoo.test import parallel_api_test, parallel_seed_test

import twinswarm
from twinswarm import tasks
from twinswarm.gym_env import HOVER_ID, REACH_ID, HoverEnv, TwinswarmEnv, TwinswarmVectorEnv, vector_env
from twinswarm.gym_env import register_envs
from twinswarm.pettingzoo_env import parallel_env

register_envs()

# Two copters 1 m apart facing the +x wall (0.4 m and 1.4 m away) in an empty 4 m x 3 m arena.
TWO_FACING_WALL = """
[arena]
size_m = [4.0, 3.0]
height_m = 2.5
[[copter]]
name = "near"
start = { pos_m = [1.6, 0.5], yaw_deg = 0.0 }
[[copter]]
name = "far"
start = { pos_m = [0.6, -0.5], yaw_deg = 0.0 }
"""

ONE_FACING_WALL = """
[arena]
size_m = [4.0, 3.0]
height_m = 2.5
[[copter]]
name = "solo"
start = { pos_m = [1.5, 0.0], yaw_deg = 0.0 }
"""


def velocity_action(forward_m_s=0.0, height_m=1.0, sim=None):
    """The normalised velocity action for a speed and height (default band 0.3 to 2 m)."""
    lo, hi = 0.3, 2.0
    return np.array([forward_m_s, 0.0, 2 * (height_m - lo) / (hi - lo) - 1, 0.0], dtype=np.float32)


def run(env, actions_fn, steps):
    """Steps a ParallelEnv `steps` times (or until no agent is left); returns the transitions."""
    out = []
    for _ in range(steps):
        if not env.agents:
            break
        out.append(env.step({a: actions_fn(a) for a in env.agents}))
    return out


def assert_same(a, b):
    """Bitwise equality of nested dicts, lists and arrays."""
    if isinstance(a, dict):
        assert a.keys() == b.keys()
        for k in a:
            assert_same(a[k], b[k])
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b)
        for x, y in zip(a, b):
            assert_same(x, y)
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    else:
        assert a == b or (isinstance(a, float) and math.isnan(a) and math.isnan(b))


def test_column_names_match_the_native_module():
    assert tuple(twinswarm.TRUTH_COLUMNS) == tasks.TRUTH_COLUMNS
    assert tuple(twinswarm.SENSOR_COLUMNS) == tasks.SENSOR_COLUMNS


# ---- PettingZoo ----

@pytest.mark.parametrize("task", ["reach", "hover", "coverage"])
def test_parallel_api(task):
    env = parallel_env(task=task, max_steps=40)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        parallel_api_test(env, num_cycles=60)
    assert env.agents == []  # every agent truncated at max_steps


def test_parallel_seed_test():
    parallel_seed_test(lambda: parallel_env(max_steps=25), num_cycles=25)


def test_parallel_spaces_and_columns():
    env = parallel_env(task="reach")
    obs, infos = env.reset(seed=0)
    assert env.possible_agents == ["finken1", "finken2"] and env.agents == env.possible_agents
    for a in env.agents:
        assert env.observation_space(a) is env.observation_space(a)
        assert env.action_space(a) is env.action_space(a)
        assert env.observation_space(a).shape == (len(env.observation_columns),)
        assert env.action_space(a) == gymnasium.spaces.Box(-1, 1, (4,), np.float32)
        assert obs[a].dtype == np.float32 and obs[a] in env.observation_space(a)
    assert env.observation_columns == tasks.SENSOR_OBS_COLUMNS + ("goal_fwd", "goal_left", "goal_up")
    assert env.state().shape == (2 * 14,)


def test_seeded_reset_replays_bit_for_bit_and_unseeded_resets_differ():
    env = parallel_env(task="reach", max_steps=200)
    action = velocity_action(0.3)

    def episode(seed=None):
        obs, _ = env.reset(seed=seed)
        return [obs] + run(env, lambda a: action, 15), list(env.sim.digest())

    first, digest1 = episode(5)
    again, digest2 = episode(5)
    assert_same(first, again)
    assert digest1 == digest2
    other, _ = episode(6)
    assert not np.array_equal(first[0]["finken1"], other[0]["finken1"])  # new goals
    # reset() without a seed continues the seeded generator: a new episode, replayed after reseeding
    _, _ = episode(5)
    next1, _ = episode()
    _, _ = episode(5)
    next2, _ = episode()
    assert_same(next1, next2)
    assert not np.array_equal(next1[0]["finken1"], first[0]["finken1"])


def test_crash_terminates_and_removes_only_that_agent():
    env = parallel_env(scene=TWO_FACING_WALL, task="hover", max_steps=200)
    env.reset(seed=1)
    crash_step = None
    for k in range(200):
        out = env.step({a: velocity_action(1.0 if a == "near" else 0.0) for a in env.agents})
        _, rewards, terms, truncs, infos = out
        if "near" in terms and terms["near"]:
            crash_step = k
            break
    assert crash_step is not None, "the copter flying into the wall at 1 m/s did not crash"
    assert infos["near"]["crashed"] is True and rewards["near"] == -10.0
    assert env.agents == ["far"] and terms["far"] is False and not infos["far"]["crashed"]
    assert env.sim.crashed().tolist() == [True, False]
    with pytest.raises(KeyError, match="near"):
        env.step({"near": velocity_action(), "far": velocity_action()})
    run(env, lambda a: velocity_action(), 5)  # the survivor flies on


def test_hover_reward_formula_and_take_off_to_one_metre():
    env = parallel_env(task="hover", max_steps=200)
    env.reset(seed=2)
    assert np.all(env.sim.truth()[:, 2] < 0.1)  # on the floor
    out = run(env, lambda a: velocity_action(0.0, 1.0), 30)  # 1.5 s
    for _, rewards, terms, _, infos in out:
        for a in env.possible_agents:
            assert rewards[a] == pytest.approx(math.exp(-infos[a]["goal_distance_m"] / 0.5), rel=1e-9)
            assert not terms[a]
    z = env.sim.truth()[:, 2]
    assert np.all(np.abs(z - 1.0) < 0.15), z
    assert all(infos[a]["goal_distance_m"] < 0.2 for a in env.possible_agents)


def test_reach_targets_avoid_walls_boxes_and_starts():
    # a 3 m x 3 m arena whose middle is a 1 m x 1 m pillar: 0.4 m from walls and pillar leaves
    # a ring 0.2 m wide for the targets
    scene = (TWO_FACING_WALL.replace("[4.0, 3.0]", "[3.0, 3.0]").replace("1.6, 0.5", "1.1, 1.1")
             .replace("0.6, -0.5", "-1.1, -1.1") + '[[box]]\npos_m = [0.0, 0.0]\nsize_m = [1.0, 1.0, 2.5]\n')
    env = parallel_env(scene=scene, task="reach", max_steps=5)
    assert len(env.task.boxes) == 1
    for seed in range(20):
        env.reset(seed=seed)
        goals, starts = env.task.goals_m, env.sim.truth()[:, :2]
        assert np.all(np.abs(goals[:, :2]) <= 1.5 - 0.4 + 1e-9)
        assert not any(env.task.boxes[0].contains(g, 0.4) for g in goals)
        assert np.all(np.linalg.norm(goals[:, None, :2] - starts[None], axis=2) >= 0.6)
        assert np.linalg.norm(goals[0, :2] - goals[1, :2]) >= 0.6
    lab = parallel_env(task="reach")
    assert len(lab.task.boxes) == 3, "the embedded lab's boxes (table, crate, pillar) are unknown"


def test_reach_goals_and_observation_agree():
    env = parallel_env(task="reach", max_steps=50)
    obs, _ = env.reset(seed=3)
    goals = env.task.goals_m
    cols = env.observation_columns
    j = [cols.index(c) for c in ("goal_fwd", "goal_left", "goal_up")]
    truth = env.sim.truth()
    for i, a in enumerate(env.possible_agents):
        d = np.linalg.norm(goals[i] - truth[i, :3])
        assert np.linalg.norm(obs[a][j]) == pytest.approx(d, rel=1e-4)
    _, rewards, _, _, infos = env.step({a: velocity_action(0.5) for a in env.agents})
    # reward = progress towards the target (no arrival, no crash on the first step)
    prev_d = np.linalg.norm(goals - truth[:, :3], axis=1)
    for i, a in enumerate(env.possible_agents):
        assert rewards[a] == pytest.approx(prev_d[i] - infos[a]["goal_distance_m"], abs=1e-5)


def test_reach_arrival_ends_the_agent_and_its_copter_hovers_on():
    env = parallel_env(task="reach", max_steps=200)
    env.reset(seed=0)
    start = env.sim.truth()[:, :3].astype(np.float64)
    env.task.goals_m = start + [[0.0, 0.0, 0.8], [1.0, 0.0, 0.8]]  # finken1's goal straight above
    arrived = None
    for k in range(100):
        _, rewards, terms, _, infos = env.step({a: velocity_action(0.0, 0.8) for a in env.agents})
        if terms.get("finken1"):
            arrived = k
            break
    assert arrived is not None, "finken1 never came within 0.2 m of the point above it"
    d = infos["finken1"]["goal_distance_m"]
    assert d < 0.2 and not infos["finken1"]["crashed"] and rewards["finken1"] > 10.0
    assert env.agents == ["finken2"]
    run(env, lambda a: velocity_action(0.0, 0.8), 20)
    z1 = env.sim.truth()[0, 2]
    assert not env.sim.crashed()[0] and abs(z1 - 0.82) < 0.2  # held where it arrived


def test_coverage_reward_sums_to_the_covered_cells():
    env = parallel_env(task="coverage", max_steps=60)
    env.reset(seed=4)
    out = run(env, lambda a: velocity_action(0.5, 1.0), 60)
    total = {a: sum(o[1][a] for o in out) for a in env.possible_agents}
    cells = int(env.task.covered.sum())
    assert cells >= 2
    for a in env.possible_agents:
        assert total[a] == pytest.approx(cells)
    frac = out[-1][4]["finken1"]["covered_fraction"]
    assert frac == pytest.approx(cells / env.task.covered.size)


def test_custom_reward_fn_replaces_the_task_reward():
    calls = []

    def height_reward(sim, prev_truth, truth, crashed):
        calls.append((prev_truth.shape, truth.shape, crashed.dtype))
        return truth[:, 2] - prev_truth[:, 2]

    env = parallel_env(task="reach", max_steps=10, reward_fn=height_reward)
    env.reset(seed=0)
    z0 = env.sim.truth()[:, 2].astype(np.float64)
    _, rewards, _, _, _ = env.step({a: velocity_action(0.0, 1.5) for a in env.agents})
    z1 = env.sim.truth()[:, 2].astype(np.float64)
    assert calls == [((2, 14), (2, 14), np.bool_)]
    assert [rewards[a] for a in env.possible_agents] == pytest.approx(list(z1 - z0))

    venv = vector_env(2, max_steps=5, reward_fn=lambda sim, p, t, c: np.full(sim.n, 7.0))
    venv.reset(seed=0)
    assert venv.step(np.zeros((2, 4)))[1].tolist() == [7.0, 7.0]

    bad = parallel_env(max_steps=10, reward_fn=lambda sim, p, t, c: np.zeros(3))
    bad.reset(seed=0)
    with pytest.raises(ValueError, match=r"reward_fn: expected shape \(2,\)"):
        bad.step({a: velocity_action() for a in bad.agents})


def test_task_instances_and_truth_obs():
    env = parallel_env(task=tasks.HoverTask(height_m=0.8, truth_obs=True), max_steps=5)
    obs, _ = env.reset(seed=0)
    assert env.observation_columns[-6:] == tasks.TRUTH_OBS_COLUMNS
    truth = env.sim.truth()
    np.testing.assert_allclose(obs["finken2"][-6:-3], truth[1, :3], atol=1e-6)
    assert env.task.goals_m[:, 2].tolist() == [0.8, 0.8]
    env2 = parallel_env(task="hover", action="rotors", max_steps=5)
    env2.reset(seed=0)
    run(env2, lambda a: np.zeros(4, np.float32), 5)


def test_parallel_env_bad_arguments():
    with pytest.raises(ValueError, match="unknown task 'fly'"):
        parallel_env(task="fly")
    with pytest.raises(TypeError, match="task"):
        parallel_env(task=3)
    with pytest.raises(ValueError, match="unknown action kind 'attitude'"):
        parallel_env(action="attitude")
    with pytest.raises(ValueError, match="max_steps"):
        parallel_env(max_steps=0)
    with pytest.raises(TypeError, match="reward_fn"):
        parallel_env(reward_fn=3)
    with pytest.raises(ValueError, match="render_mode"):
        parallel_env(render_mode="human")
    env = parallel_env(max_steps=10)
    with pytest.raises(RuntimeError, match="reset"):
        env.step({})
    env.reset(seed=0)
    ok = velocity_action()
    with pytest.raises(KeyError, match="finken9"):
        env.step({"finken1": ok, "finken2": ok, "finken9": ok})
    with pytest.raises(ValueError, match=r"no action for live agent\(s\) \['finken2'\]"):
        env.step({"finken1": ok})
    with pytest.raises(ValueError, match="'finken2': NaN"):
        env.step({"finken1": ok, "finken2": np.array([0, np.nan, 0, 0])})
    with pytest.raises(ValueError, match="'finken1': expected 4 numbers"):
        env.step({"finken1": np.zeros(3), "finken2": ok})
    assert env.sim.tick == 0  # nothing was stepped by the rejected calls
    env.render_mode = "ansi"
    assert "finken1" in env.render()


# ---- Gymnasium: one copter ----

@pytest.mark.parametrize("env_id", [HOVER_ID, REACH_ID])
def test_check_env(env_id):
    env = gymnasium.make(env_id, max_steps=20)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env.unwrapped)
        env.reset(seed=0)  # through the passive checker and order enforcing of gymnasium.make
        env.step(env.action_space.sample())
    assert isinstance(env.unwrapped, TwinswarmEnv)
    env.close()


def test_single_env_truncates_and_crashes():
    env = HoverEnv(max_steps=3)
    env.reset(seed=0)
    flags = [env.step(velocity_action())[2:4] for _ in range(3)]
    assert flags == [(False, False), (False, False), (False, True)]
    env = TwinswarmEnv(task="hover", scene=ONE_FACING_WALL, max_steps=200)
    env.reset(seed=0)
    for _ in range(200):
        _, reward, terminated, truncated, info = env.step(velocity_action(1.0))
        if terminated:
            break
    assert terminated and info["crashed"] and reward == -10.0 and not truncated


def test_single_env_bad_arguments():
    with pytest.raises(ValueError, match="exactly one copter"):
        TwinswarmEnv(scene=TWO_FACING_WALL)
    with pytest.raises(TypeError, match="task is fixed"):
        HoverEnv(task="reach")
    env = HoverEnv(max_steps=5)
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"expected shape \(1, 4\)"):
        env.step(np.zeros(5))
    with pytest.raises(ValueError, match="NaN"):
        env.step(np.array([np.nan, 0, 0, 0]))


# ---- Gymnasium: vector ----

def test_vector_env_shapes_and_spaces():
    envs = vector_env(num_envs=3, max_steps=5)
    assert isinstance(envs, gymnasium.vector.VectorEnv)
    assert envs.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    single = HoverEnv()
    assert envs.single_observation_space == single.observation_space
    assert envs.single_action_space == single.action_space
    assert envs.observation_space.shape == (3, single.observation_space.shape[0])
    assert envs.action_space.shape == (3, 4)
    obs, infos = envs.reset(seed=0)
    assert obs.dtype == np.float32 and obs in envs.observation_space and infos == {}
    obs, rewards, terms, truncs, infos = envs.step(envs.action_space.sample())
    assert obs in envs.observation_space
    assert rewards.dtype == np.float64 and rewards.shape == (3,)
    assert terms.dtype == np.bool_ and truncs.dtype == np.bool_ and terms.shape == truncs.shape == (3,)
    assert infos["crashed"].tolist() == [False] * 3 and infos["_crashed"].all()
    assert isinstance(gymnasium.make_vec(HOVER_ID, num_envs=2), TwinswarmVectorEnv)
    reach = gymnasium.make_vec(REACH_ID, num_envs=2, max_steps=4)
    assert isinstance(reach, TwinswarmVectorEnv) and reach.runners[0].task.name == "reach"


def test_vector_env_next_step_autoreset():
    envs = vector_env(num_envs=2, max_steps=3)
    envs.reset(seed=0)
    a = np.zeros((2, 4), np.float32)
    for k in range(3):
        _, _, terms, truncs, _ = envs.step(a)
    assert truncs.tolist() == [True, True] and terms.tolist() == [False, False]
    obs, rewards, terms, truncs, infos = envs.step(a)  # the reset step: actions ignored
    assert rewards.tolist() == [0.0, 0.0] and not terms.any() and not truncs.any()
    assert [s.tick for s in envs.sims] == [0, 0] and infos == {}
    assert obs in envs.observation_space
    envs.step(a)
    assert [s.tick for s in envs.sims] == [1, 1]


def test_vector_env_same_step_autoreset():
    envs = vector_env(num_envs=2, max_steps=3, autoreset_mode="same_step")
    assert envs.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    envs.reset(seed=0)
    a = np.zeros((2, 4), np.float32)
    envs.step(a)
    envs.step(a)
    obs, rewards, terms, truncs, infos = envs.step(a)
    assert truncs.all() and infos["_final_obs"].all() and infos["_final_info"].all()
    assert [s.tick for s in envs.sims] == [0, 0]  # already reset, in the same step
    for i in range(2):
        assert infos["final_obs"][i].shape == obs[i].shape
        assert not np.array_equal(infos["final_obs"][i], obs[i])
    assert infos["final_info"]["crashed"].tolist() == [False, False]  # Gymnasium batches final_info too
    _, _, _, truncs, infos = envs.step(a)
    assert not truncs.any() and "final_obs" not in infos


def test_vector_env_disabled_autoreset_and_reset_mask():
    envs = vector_env(num_envs=2, max_steps=2, autoreset_mode=AutoresetMode.DISABLED)
    envs.reset(seed=0)
    a = np.zeros((2, 4), np.float32)
    envs.step(a)
    assert envs.step(a)[3].all()
    with pytest.raises(RuntimeError, match="reset_mask"):
        envs.step(a)
    obs_before = envs._obs.copy()
    obs, _ = envs.reset(options={"reset_mask": np.array([True, False])})
    assert [s.tick for s in envs.sims] == [0, 2]
    np.testing.assert_array_equal(obs[1], obs_before[1])
    with pytest.raises(RuntimeError, match=r"world\(s\) \[1\]"):
        envs.step(a)


def test_vector_env_is_deterministic_and_equals_single_envs():
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (12, 3, 4)).astype(np.float32)

    def roll(envs):
        out = [envs.reset(seed=10)[0]]
        for a in actions:
            out.append(envs.step(a)[:4])
        return out, [d for s in envs.sims for d in s.digest()]

    a, digest_a = roll(vector_env(num_envs=3, task="reach", max_steps=8))
    b, digest_b = roll(vector_env(num_envs=3, task="reach", max_steps=8))
    assert_same(a, b)
    assert digest_a == digest_b
    # world 1 is the single environment reset with seed 11, given the same actions
    single = TwinswarmEnv(task="reach", max_steps=8)
    obs, _ = single.reset(seed=11)
    np.testing.assert_array_equal(obs, a[0][1])
    for k in range(8):
        obs, r, term, trunc, _ = single.step(actions[k, 1])
        np.testing.assert_array_equal(obs, a[k + 1][0][1])
        assert r == a[k + 1][1][1] and trunc == a[k + 1][3][1]


def test_vector_env_bad_arguments():
    with pytest.raises(ValueError, match="num_envs"):
        vector_env(num_envs=0)
    with pytest.raises(ValueError, match="autoreset_mode"):
        vector_env(num_envs=1, autoreset_mode="sometimes")
    envs = vector_env(num_envs=2, max_steps=5)
    with pytest.raises(RuntimeError, match="reset"):
        envs.step(np.zeros((2, 4)))
    with pytest.raises(ValueError, match="one per world"):
        envs.reset(seed=[1, 2, 3])
    envs.reset(seed=[1, None])
    with pytest.raises(ValueError, match=r"expected shape \(2, 4\)"):
        envs.step(np.zeros((3, 4)))
    with pytest.raises(ValueError, match="world 1: NaN"):
        envs.step(np.array([[0, 0, 0, 0], [0, 0, np.inf, 0]]))
    with pytest.raises(ValueError, match="reset_mask"):
        envs.reset(options={"reset_mask": [True, False]})
