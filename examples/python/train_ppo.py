"""Train a PPO policy (stable-baselines3) on Twinswarm, then fly it once and report.

    python train_ppo.py hover  [--num-envs 8] [--steps 200000] [--out ppo_hover.zip] [--curve ppo_hover_curve.csv]
    python train_ppo.py swarm  [--task coverage] [--copies 4] [--steps 200000]

`hover`: B one-copter worlds of `twinswarm.vector_env` (one `Sim` each, all stepped in one
`twinswarm.step_many` call), seen by stable-baselines3 through the small `SB3VecEnv` adapter
below (Gymnasium vector envs are not SB3 VecEnvs; SB3 wants same-step autoreset with
`terminal_observation` in the infos, which `autoreset_mode="same_step"` gives).
`swarm`: the PettingZoo parallel env (every copter an agent, one shared policy) through
`BlackDeath` below (an agent that has ended keeps an all-zero observation and reward 0 until
the whole episode ends, as SB3 needs a fixed number of agents) and SuperSuit's
`pettingzoo_env_to_vec_env_v1`, `ConcatVecEnv` and `SB3VecEnvWrapper` (what
`concat_vec_envs_v1` builds, minus its pickled copies of the env).

Needs `pip install stable-baselines3` (and `supersuit` for `swarm`); not run by the tests.
"""
from __future__ import annotations

import argparse

import numpy as np

import twinswarm
from twinswarm.gym_env import vector_env
from twinswarm.pettingzoo_env import parallel_env

from pettingzoo.utils.wrappers import BaseParallelWrapper
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.utils import set_random_seed
from stable_baselines3.common.vec_env import VecEnv, VecMonitor


class Curve(BaseCallback):
    """The learning curve: after each rollout, the mean return and length of the last 100
    finished episodes, written as CSV lines `timesteps,mean_return,mean_length,seconds`."""

    def __init__(self, path):
        super().__init__()
        self.path = path
        self.rows = []

    def _on_training_start(self):
        import time

        self.t0 = time.perf_counter()

    def _on_step(self):
        return True

    def _on_rollout_end(self):
        import time

        buf = self.model.ep_info_buffer
        if buf:
            row = (self.num_timesteps, float(np.mean([e["r"] for e in buf])), float(np.mean([e["l"] for e in buf])),
                   time.perf_counter() - self.t0)
            self.rows.append(row)
            with open(self.path, "w") as f:
                f.write("timesteps,mean_return,mean_length,seconds\n")
                f.writelines(f"{t},{r:.3f},{l:.1f},{s:.1f}\n" for t, r, l, s in self.rows)


class SB3VecEnv(VecEnv):
    """A `twinswarm.gym_env.TwinswarmVectorEnv` (same-step autoreset) as an SB3 VecEnv."""

    def __init__(self, venv):
        if venv.metadata["autoreset_mode"].name != "SAME_STEP":
            raise ValueError("SB3VecEnv needs a vector env with autoreset_mode='same_step'")
        self.venv = venv  # before VecEnv.__init__, which calls get_attr("render_mode")
        self._actions = None
        super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)

    def reset(self):
        seeds = None if all(s is None for s in self._seeds) else self._seeds
        obs, _ = self.venv.reset(seed=seeds)
        self.reset_infos = [{} for _ in range(self.num_envs)]
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions):
        self._actions = np.asarray(actions, dtype=np.float32)

    def step_wait(self):
        obs, rewards, terminated, truncated, infos = self.venv.step(self._actions)
        dones = terminated | truncated
        out = []
        for i in range(self.num_envs):
            info = {}
            if dones[i]:
                info["terminal_observation"] = infos["final_obs"][i]
                info["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
            out.append(info)
        return obs, rewards.astype(np.float32), dones, out

    def close(self):
        self.venv.close()

    def get_attr(self, attr_name, indices=None):
        return [getattr(self.venv, attr_name)] * len(list(self._get_indices(indices)))

    def set_attr(self, attr_name, value, indices=None):
        setattr(self.venv, attr_name, value)

    def env_method(self, method_name, *args, indices=None, **kwargs):
        return [getattr(self.venv.runners[i].task, method_name)(*args, **kwargs) for i in self._get_indices(indices)]

    def env_is_wrapped(self, wrapper_class, indices=None):
        return [False] * len(list(self._get_indices(indices)))


class BlackDeath(BaseParallelWrapper):
    """SuperSuit's `black_death_v3` as its PR #265 fixes it: SuperSuit 3.11.0 ends the episode
    only when every agent is terminated *and* truncated, so an episode that ends by truncation
    never ends there."""

    def reset(self, seed=None, options=None):
        obs, infos = self.env.reset(seed=seed, options=options)
        self.agents = list(self.env.possible_agents)
        return obs, infos

    def step(self, actions):
        obs, rewards, terms, truncs, infos = self.env.step({a: actions[a] for a in self.env.agents})
        ended = not self.env.agents
        zeros = {a: np.zeros(self.observation_space(a).shape, np.float32) for a in self.agents if a not in obs}
        out = (
            {**zeros, **obs},
            {a: rewards.get(a, 0.0) for a in self.agents},
            {a: ended and terms.get(a, True) for a in self.agents},
            {a: ended and truncs.get(a, False) for a in self.agents},
            {a: infos.get(a, {}) for a in self.agents},
        )
        if ended:
            self.agents = []
        return out


def train_hover(args):
    venv = VecMonitor(SB3VecEnv(vector_env(num_envs=args.num_envs, task="hover", max_steps=args.max_steps,
                                           autoreset_mode="same_step")))
    venv.seed(args.seed)
    model = PPO("MlpPolicy", venv, n_steps=256, batch_size=256, gamma=0.98, seed=args.seed, verbose=1)
    model.learn(total_timesteps=args.steps, callback=Curve(args.curve))
    model.save(args.out)
    env = twinswarm.gym_env.HoverEnv(max_steps=args.max_steps)
    obs, _ = env.reset(seed=args.seed + 1000)
    total, done = 0.0, False
    while not done:
        action, _ = model.predict(obs, deterministic=True)
        obs, reward, terminated, truncated, info = env.step(action)
        total += reward
        done = terminated or truncated
    print(f"evaluation: return {total:.1f} over {env.runner.steps} steps, "
          f"{info['goal_distance_m']:.2f} m from the hover point at the end, crashed: {info['crashed']}")


def train_swarm(args):
    from supersuit import pettingzoo_env_to_vec_env_v1
    from supersuit.vector.concat_vec_env import ConcatVecEnv
    from supersuit.vector.sb3_vector_wrapper import SB3VecEnvWrapper

    def copy_fn(k):
        # a new env per copy: concat_vec_envs_v1 would cloudpickle one, and a Sim does not pickle
        return lambda: pettingzoo_env_to_vec_env_v1(
            BlackDeath(parallel_env(task=args.task, max_steps=args.max_steps, seed=args.seed + k)))

    venv = VecMonitor(SB3VecEnvWrapper(ConcatVecEnv([copy_fn(k) for k in range(args.copies)])))
    # SuperSuit's ConcatVecEnv has no `seed()`, which PPO(seed=...) calls: the copies are
    # seeded at construction above; torch and numpy here.
    set_random_seed(args.seed)
    model = PPO("MlpPolicy", venv, n_steps=256, batch_size=256, gamma=0.98, verbose=1)
    model.learn(total_timesteps=args.steps, callback=Curve(args.curve))
    model.save(args.out)
    env = parallel_env(task=args.task, max_steps=args.max_steps)
    obs, _ = env.reset(seed=args.seed + 1000)
    totals = dict.fromkeys(env.possible_agents, 0.0)
    while env.agents:
        actions = {a: model.predict(obs[a], deterministic=True)[0] for a in env.agents}
        obs, rewards, _, _, infos = env.step(actions)
        for a, r in rewards.items():
            totals[a] += r
    print(f"evaluation ({args.task}): returns {totals}, crashed {env.sim.crashed().tolist()}")


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("mode", choices=["hover", "swarm"])
    p.add_argument("--task", default="coverage", choices=sorted(twinswarm.tasks.TASKS), help="swarm task")
    p.add_argument("--num-envs", type=int, default=8, help="hover: worlds stepped together")
    p.add_argument("--copies", type=int, default=4, help="swarm: copies of the swarm env")
    p.add_argument("--steps", type=int, default=200_000, help="total environment steps")
    p.add_argument("--max-steps", type=int, default=400, help="control steps per episode (20 per second)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="where to save the model (default ppo_<mode>.zip)")
    p.add_argument("--curve", default=None, help="the learning curve, CSV (default ppo_<mode>_curve.csv)")
    args = p.parse_args()
    args.out = args.out or f"ppo_{args.mode}.zip"
    args.curve = args.curve or f"ppo_{args.mode}_curve.csv"
    (train_hover if args.mode == "hover" else train_swarm)(args)


if __name__ == "__main__":
    main()
