"""A PettingZoo `ParallelEnv` over one `twinswarm.Sim`: every copter is an agent.

    env = twinswarm.pettingzoo_env.parallel_env(task="reach", max_steps=500)
    obs, infos = env.reset(seed=1)
    while env.agents:
        actions = {a: env.action_space(a).sample() for a in env.agents}
        obs, rewards, terminations, truncations, infos = env.step(actions)

Agents are the copters' names (`Sim.names`), in id order. One `step` is one control step
(`Sim.dt`, 50 ms). An agent terminates when its copter crashes or its task says it is done
(reach: arrived), and is then removed from `agents`; every agent is truncated after
`max_steps` steps. A removed agent's copter stays in the arena: a wreck, or (done without a
crash) hovering where it is. Spaces, rewards and the action mapping: `twinswarm.tasks`.
"""
from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
from pettingzoo import ParallelEnv

import twinswarm
from twinswarm.tasks import RewardFn, Task, TaskRunner, check_actions, info_rows

_SEED_BOUND = 2**63


class TwinswarmParallelEnv(ParallelEnv):
    """The swarm as a PettingZoo parallel environment; build it with `parallel_env`.

    - `observation_space(agent)`: Box float32 (k,), columns `env.observation_columns`
      (`twinswarm.tasks.SENSOR_OBS_COLUMNS` + the task's columns), clipped to the bounds.
    - `action_space(agent)`: Box(-1, 1, (4,), float32), mapped by `twinswarm.tasks.ActionMap`.
    - `state()`: `Sim.truth()` flattened, float32 (n * 14,), for centralised critics.
    - `reset(seed=s)` restarts the Sim with seed s and reseeds the task's generator (goals);
      `reset()` draws the next Sim seed from that generator, so a seeded run replays exactly.
    - Info per agent: `crashed` and the task's numbers (`goal_distance_m`, `covered_fraction`).
    """

    metadata = {"name": "twinswarm_v0", "render_modes": ["ansi"], "is_parallelizable": True}

    def __init__(self, scene: Any = None, task: str | Task = "reach", seed: int | None = None, max_steps: int = 500,
                 action: str = "velocity", render_mode: str | None = None, reward_fn: RewardFn | None = None,
                 threads: int = 1):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode: expected None or one of {self.metadata['render_modes']}, got {render_mode!r}")
        self.render_mode = render_mode
        self.sim = twinswarm.Sim(scene=scene, seed=seed, threads=threads)
        self.runner = TaskRunner(self.sim, task, scene=scene, action=action, reward_fn=reward_fn, max_steps=max_steps)
        self.task = self.runner.task
        self.possible_agents = list(self.sim.names)
        self.agents: list[str] = []
        self._index = {a: i for i, a in enumerate(self.possible_agents)}
        self.observation_columns = self.task.observation_columns
        low, high = self.runner.obs_low, self.runner.obs_high
        self.observation_spaces = {a: gymnasium.spaces.Box(low, high, dtype=np.float32) for a in self.possible_agents}
        self.action_spaces = {a: gymnasium.spaces.Box(-1.0, 1.0, (4,), np.float32) for a in self.possible_agents}
        n = len(self.possible_agents)
        self.state_space = gymnasium.spaces.Box(-np.inf, np.inf, (n * 14,), np.float32)
        self._first_seed = seed
        self._rng = np.random.default_rng(seed)
        self._started = False

    def observation_space(self, agent: str) -> gymnasium.spaces.Box:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> gymnasium.spaces.Box:
        return self.action_spaces[agent]

    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None):
        if seed is None:
            seed = self._first_seed  # the constructor's seed, for the first reset only
        self._first_seed = None
        if seed is not None:
            self._rng = np.random.default_rng(seed)
            sim_seed = seed
        else:
            sim_seed = int(self._rng.integers(_SEED_BOUND))
        obs = self.runner.reset(sim_seed, self._rng)
        self.agents = list(self.possible_agents)
        self._started = True
        observations = {a: obs[i].copy() for i, a in enumerate(self.agents)}
        infos = {a: {} for a in self.agents}
        return observations, infos

    def step(self, actions: dict[str, Any]):
        if not self._started:
            raise RuntimeError("step() before reset(): call reset() first")
        if not self.agents:
            raise RuntimeError("step() with no live agents: every episode has ended; call reset()")
        if not isinstance(actions, dict):
            raise TypeError(f"actions: expected a dict agent -> action, got {type(actions).__name__}")
        unknown = [a for a in actions if a not in self._index]
        if unknown:
            raise KeyError(f"actions: unknown agent(s) {unknown}; agents are {self.possible_agents}")
        ended = [a for a in actions if a not in self.agents]
        if ended:
            raise KeyError(f"actions: agent(s) {ended} have terminated or been truncated; live agents are {self.agents}")
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"actions: no action for live agent(s) {missing}")

        live = list(self.agents)
        ids = [self._index[a] for a in live]
        a = check_actions(_stack([actions[a] for a in live], live), len(live), lambda k: f"agent {live[k]!r}")
        self.runner.act(a, ids)
        self.sim.step(1)
        obs, reward, crashed, terminated, info = self.runner.collect()
        truncated = self.runner.truncated

        observations, rewards, terminations, truncations, infos = {}, {}, {}, {}, {}
        for agent, i in zip(live, ids):
            observations[agent] = obs[i].copy()
            rewards[agent] = float(reward[i])
            terminations[agent] = bool(terminated[i])
            truncations[agent] = bool(truncated and not terminated[i])
            infos[agent] = info_rows(info, i)
        self.agents = [a for a in live if not (terminations[a] or truncations[a])]
        done_flying = [self._index[a] for a in live if terminations[a] and not crashed[self._index[a]]]
        if self.agents:
            self.runner.actions.hold(self.sim, done_flying)
        return observations, rewards, terminations, truncations, infos

    def render(self) -> str | None:
        if self.render_mode is None:
            gymnasium.logger.warn("render() without a render_mode: pass render_mode='ansi' to parallel_env")
            return None
        return self.runner.render_text()

    def state(self) -> np.ndarray:
        return np.asarray(self.sim.truth(), dtype=np.float32).reshape(-1).copy()

    def close(self) -> None:
        pass


def _stack(rows: list[Any], live: list[str]) -> Any:
    """The agents' actions as one (m, 4) array; ValueError naming an agent whose action does
    not have 4 numbers."""
    out = []
    for agent, row in zip(live, rows):
        try:
            r = np.asarray(row, dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise TypeError(f"action for agent {agent!r}: expected 4 numbers, got {type(row).__name__}: {e}") from None
        if r.shape not in ((4,), (1, 4)):
            raise ValueError(f"action for agent {agent!r}: expected 4 numbers, got shape {r.shape}")
        out.append(r.reshape(4))
    return np.stack(out)


def parallel_env(scene: Any = None, task: str | Task = "reach", seed: int | None = None, max_steps: int = 500,
                 action: str = "velocity", render_mode: str | None = None, reward_fn: RewardFn | None = None,
                 threads: int = 1) -> TwinswarmParallelEnv:
    """A PettingZoo parallel environment over `twinswarm.Sim(scene, seed, threads)`.

    scene: a scene file, TOML text, or None for the embedded lab (2 copters).
    task: "reach", "hover", "coverage" (`twinswarm.tasks.TASKS`) or a `Task` instance (copied).
    seed: the seed of the first `reset()` when it is given none.
    max_steps: control steps per episode before truncation.
    action: "velocity" or "rotors" (`twinswarm.tasks.ActionMap`).
    render_mode: None or "ansi" (a text table of the copters).
    reward_fn: `f(sim, prev_truth, truth, crashed) -> (n,)`, replacing the task's reward.
    threads: worker threads of the Sim's step (the same bits for any value).
    """
    return TwinswarmParallelEnv(scene=scene, task=task, seed=seed, max_steps=max_steps, action=action,
                                render_mode=render_mode, reward_fn=reward_fn, threads=threads)


__all__ = ["TwinswarmParallelEnv", "parallel_env"]
