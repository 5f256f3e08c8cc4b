"""Gymnasium environments: one copter per world, and B worlds stepped together.

    env = gymnasium.make("twinswarm/Hover-v0")           # TwinswarmEnv, task "hover"
    envs = twinswarm.vector_env(num_envs=8)              # TwinswarmVectorEnv, one Sim per world

Each world is a `twinswarm.Sim` of `SINGLE_COPTER_SCENE` (the lab's 4 m x 3 m x 2.5 m
arena with walls, no boxes, one FINken at the centre, on the floor) unless a one-copter
`scene` is given. One step is one control step (`Sim.dt`, 50 ms). An episode terminates when
the copter crashes or the task is done, and is truncated after `max_steps` steps.
Observations, rewards and actions: `twinswarm.tasks` (the same as the PettingZoo env's).
"""
from __future__ import annotations

from typing import Any, Sequence

import gymnasium
import numpy as np
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

import twinswarm
from twinswarm.tasks import RewardFn, Task, TaskRunner, check_actions, info_rows

HOVER_ID = "twinswarm/Hover-v0"
REACH_ID = "twinswarm/Reach-v0"
_SEED_BOUND = 2**63

SINGLE_COPTER_SCENE = """\
# One FINken III in the lab's arena (4 m x 3 m, 2.5 m high, walls, no boxes): the world of
# twinswarm.gym_env's single-agent environments.
name = "single"

[sim]
seed = 1

[arena]
size_m = [4.0, 3.0]
height_m = 2.5
walls = true

[[copter]]
name = "finken1"
kind = "virtual"
airframe = "finken3"
start = { pos_m = [0.0, 0.0], yaw_deg = 0.0 }
mode = "velocity"
"""


def _single_copter_sim(scene: Any, threads: int = 1) -> Any:
    sim = twinswarm.Sim(scene=SINGLE_COPTER_SCENE if scene is None else scene, threads=threads)
    if sim.n != 1:
        raise ValueError(f"scene: a single-agent environment needs exactly one copter, the scene has {sim.n} "
                         f"({list(sim.names)}); use twinswarm.pettingzoo_env.parallel_env for swarms")
    return sim


def _obs_space(runner: TaskRunner) -> gymnasium.spaces.Box:
    return gymnasium.spaces.Box(runner.obs_low, runner.obs_high, dtype=np.float32)


def _action_space() -> gymnasium.spaces.Box:
    return gymnasium.spaces.Box(-1.0, 1.0, (4,), np.float32)


class TwinswarmEnv(gymnasium.Env):
    """One copter, one task, as a Gymnasium environment.

    - observation_space: Box float32 (k,), columns `env.observation_columns`, clipped.
    - action_space: Box(-1, 1, (4,), float32), mapped by `twinswarm.tasks.ActionMap`.
    - `reset(seed=s)` restarts the Sim with seed s and seeds `np_random` (task goals);
      `reset()` draws the next Sim seed from `np_random`.
    - info: `crashed` and the task's numbers.
    """

    metadata = {"render_modes": ["ansi"], "render_fps": 20}

    def __init__(self, task: str | Task = "hover", scene: Any = None, max_steps: int = 500, action: str = "velocity",
                 render_mode: str | None = None, reward_fn: RewardFn | None = None, threads: int = 1):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode: expected None or one of {self.metadata['render_modes']}, got {render_mode!r}")
        self.render_mode = render_mode
        self.sim = _single_copter_sim(scene, threads)
        self.runner = TaskRunner(self.sim, task, scene=scene if scene is not None else SINGLE_COPTER_SCENE,
                                 action=action, reward_fn=reward_fn, max_steps=max_steps)
        self.task = self.runner.task
        self.observation_columns = self.task.observation_columns
        self.observation_space = _obs_space(self.runner)
        self.action_space = _action_space()

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        sim_seed = seed if seed is not None else int(self.np_random.integers(_SEED_BOUND))
        obs = self.runner.reset(sim_seed, self.np_random)
        return obs[0].copy(), {}

    def step(self, action: Any):
        a = check_actions(action, 1, lambda _k: "the copter")
        self.runner.act(a, [0])
        self.sim.step(1)
        obs, reward, _crashed, terminated, info = self.runner.collect()
        truncated = self.runner.truncated and not terminated[0]
        return obs[0].copy(), float(reward[0]), bool(terminated[0]), bool(truncated), info_rows(info, 0)

    def render(self) -> str | None:
        if self.render_mode is None:
            gymnasium.logger.warn("render() without a render_mode: make the env with render_mode='ansi'")
            return None
        return self.runner.render_text()


class HoverEnv(TwinswarmEnv):
    """`twinswarm/Hover-v0`: one copter holds the point 1 m above its start
    (`twinswarm.tasks.HoverTask`)."""

    def __init__(self, **kwargs: Any):
        if "task" in kwargs:
            raise TypeError("HoverEnv: the task is fixed ('hover'); use TwinswarmEnv(task=...) for another")
        super().__init__(task="hover", **kwargs)


def _autoreset_mode(mode: str | AutoresetMode) -> AutoresetMode:
    if isinstance(mode, AutoresetMode):
        return mode
    for m in AutoresetMode:
        if mode in (m.value, m.name, m.name.lower()):
            return m
    raise ValueError(f"autoreset_mode: expected a gymnasium.vector.AutoresetMode or one of "
                     f"{[m.name.lower() for m in AutoresetMode]}, got {mode!r}")


class TwinswarmVectorEnv(gymnasium.vector.VectorEnv):
    """B independent one-copter worlds (each its own `Sim` and task), stepped in one call of
    `twinswarm.step_many` (threads, GIL released).

    - single_observation_space / single_action_space: those of `TwinswarmEnv`;
      observation_space (B, k) and action_space (B, 4) are their batches.
    - `reset(seed=s)` seeds world i with s + i (a list gives one seed per world);
      `options={"reset_mask": bool (B,)}` resets only the masked worlds.
    - `metadata["autoreset_mode"]` (default `AutoresetMode.NEXT_STEP`), as in Gymnasium 1.x:
      NEXT_STEP: the step after a world terminated or truncated resets it instead of stepping
        it (its action is ignored) and returns its first observation, reward 0, not
        terminated, not truncated.
      SAME_STEP: a world that ends is reset within the same step; the returned observation is
        the new episode's first, and `infos["final_obs"][i]` / `infos["final_info"][i]` (masks
        `infos["_final_obs"]`, `infos["_final_info"]`) hold the last episode's.
      DISABLED: no reset; stepping a world that has ended raises RuntimeError.
    - infos: Gymnasium's dict of arrays with `_key` masks (`crashed`, task numbers).
    """

    def __init__(self, num_envs: int = 8, task: str | Task = "hover", scene: Any = None, max_steps: int = 500,
                 action: str = "velocity", reward_fn: RewardFn | None = None,
                 autoreset_mode: str | AutoresetMode = AutoresetMode.NEXT_STEP, render_mode: str | None = None):
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs: expected a positive integer, got {num_envs!r}")
        if render_mode is not None and render_mode != "ansi":
            raise ValueError(f"render_mode: expected None or 'ansi', got {render_mode!r}")
        mode = _autoreset_mode(autoreset_mode)
        self.num_envs = int(num_envs)
        self.render_mode = render_mode
        self.metadata = {"autoreset_mode": mode, "render_modes": ["ansi"]}
        scene_for_boxes = scene if scene is not None else SINGLE_COPTER_SCENE
        self.runners = [TaskRunner(_single_copter_sim(scene), task, scene=scene_for_boxes, action=action,
                                   reward_fn=reward_fn, max_steps=max_steps) for _ in range(self.num_envs)]
        self.sims = [r.sim for r in self.runners]
        self.observation_columns = self.runners[0].task.observation_columns
        self.single_observation_space = _obs_space(self.runners[0])
        self.single_action_space = _action_space()
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._rngs = [np.random.default_rng() for _ in range(self.num_envs)]
        self._obs = np.zeros(self.observation_space.shape, dtype=np.float32)
        self._ended = np.zeros(self.num_envs, dtype=bool)
        self._started = False

    @property
    def autoreset_mode(self) -> AutoresetMode:
        return self.metadata["autoreset_mode"]

    def _reset_world(self, i: int, seed: int | None) -> None:
        if seed is not None:
            self._rngs[i] = np.random.default_rng(seed)
            sim_seed = seed
        else:
            sim_seed = int(self._rngs[i].integers(_SEED_BOUND))
        self._obs[i] = self.runners[i].reset(sim_seed, self._rngs[i])[0]
        self._ended[i] = False

    def reset(self, *, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None):
        if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
            super().reset(seed=int(seed))
            seeds: list[int | None] = [int(seed) + i for i in range(self.num_envs)]
        elif seed is None:
            seeds = [None] * self.num_envs
        else:
            seeds = list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(f"seed: a list of seeds needs one per world ({self.num_envs}), got {len(seeds)}")
        mask = self._reset_mask(options)
        if not self._started and not mask.all():
            raise RuntimeError("reset(options={'reset_mask': ...}) before a full reset(): reset every world first")
        for i in np.flatnonzero(mask):
            self._reset_world(int(i), seeds[i])
        self._started = True
        return self._obs.copy(), {}

    def _reset_mask(self, options: dict[str, Any] | None) -> np.ndarray:
        if not options or "reset_mask" not in options:
            return np.ones(self.num_envs, dtype=bool)
        mask = options["reset_mask"]
        if not isinstance(mask, np.ndarray) or mask.dtype != np.bool_ or mask.shape != (self.num_envs,):
            raise ValueError(f"options['reset_mask']: expected a numpy bool array of shape ({self.num_envs},), got {mask!r}")
        if not mask.any():
            raise ValueError("options['reset_mask']: no world selected (all False)")
        return mask

    def step(self, actions: Any):
        if not self._started:
            raise RuntimeError("step() before reset(): call reset() first")
        a = check_actions(actions, self.num_envs, lambda i: f"world {i}")
        mode = self.autoreset_mode
        if mode == AutoresetMode.DISABLED and self._ended.any():
            raise RuntimeError(f"step(): world(s) {np.flatnonzero(self._ended).tolist()} have ended and autoreset is "
                               f"disabled; reset them with reset(options={{'reset_mask': mask}})")
        rewards = np.zeros(self.num_envs, dtype=np.float64)
        terminations = np.zeros(self.num_envs, dtype=bool)
        truncations = np.zeros(self.num_envs, dtype=bool)
        infos: dict[str, Any] = {}

        restarting = self._ended.copy() if mode == AutoresetMode.NEXT_STEP else np.zeros(self.num_envs, dtype=bool)
        stepping = np.flatnonzero(~restarting)
        for i in stepping:
            self.runners[i].act(a[i:i + 1], [0])
        if len(stepping):
            twinswarm.step_many([self.sims[i] for i in stepping], steps=1)

        for i in range(self.num_envs):
            if restarting[i]:
                self._reset_world(i, None)
                infos = self._add_info(infos, {}, i)
                continue
            obs, reward, _crashed, terminated, info = self.runners[i].collect()
            env_info = info_rows(info, 0)
            rewards[i], terminations[i] = reward[0], terminated[0]
            truncations[i] = self.runners[i].truncated and not terminated[0]
            self._obs[i] = obs[0]
            if mode == AutoresetMode.SAME_STEP and (terminations[i] or truncations[i]):
                infos = self._add_info(infos, {"final_obs": obs[0].copy(), "final_info": env_info}, i)
                self._reset_world(i, None)
                env_info = {}
            infos = self._add_info(infos, env_info, i)
        if mode != AutoresetMode.SAME_STEP:
            self._ended = terminations | truncations
        return self._obs.copy(), rewards, terminations, truncations, infos

    def render(self) -> tuple[str, ...] | None:
        if self.render_mode is None:
            gymnasium.logger.warn("render() without a render_mode: make the env with render_mode='ansi'")
            return None
        return tuple(r.render_text() for r in self.runners)


def vector_env(num_envs: int = 8, task: str | Task = "hover", scene: Any = None, max_steps: int = 500,
               action: str = "velocity", reward_fn: RewardFn | None = None,
               autoreset_mode: str | AutoresetMode = AutoresetMode.NEXT_STEP,
               render_mode: str | None = None) -> TwinswarmVectorEnv:
    """`num_envs` one-copter worlds of `task` as one `gymnasium.vector.VectorEnv`
    (`TwinswarmVectorEnv`); also `gymnasium.make_vec("twinswarm/Hover-v0", num_envs)`."""
    return TwinswarmVectorEnv(num_envs=num_envs, task=task, scene=scene, max_steps=max_steps, action=action,
                              reward_fn=reward_fn, autoreset_mode=autoreset_mode, render_mode=render_mode)


def register_envs() -> None:
    """Registers `twinswarm/Hover-v0` and `twinswarm/Reach-v0` with Gymnasium (idempotent);
    `gymnasium.make_vec` on them builds a `TwinswarmVectorEnv`."""
    for env_id, entry_point, kwargs in ((HOVER_ID, "twinswarm.gym_env:HoverEnv", {}),
                                        (REACH_ID, "twinswarm.gym_env:TwinswarmEnv", {"task": "reach"})):
        if env_id not in gymnasium.registry:
            gymnasium.register(id=env_id, entry_point=entry_point, vector_entry_point="twinswarm.gym_env:vector_env",
                               kwargs=kwargs)


__all__ = ["TwinswarmEnv", "HoverEnv", "TwinswarmVectorEnv", "vector_env", "register_envs", "SINGLE_COPTER_SCENE",
           "HOVER_ID", "REACH_ID"]
