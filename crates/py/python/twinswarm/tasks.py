"""Tasks for the reinforcement-learning environments, and the runner they share.

A task says what the copters are asked to do: what each copter observes, what it is
rewarded for and when its episode ends. The environments (`twinswarm.pettingzoo_env`,
`twinswarm.gym_env`) own a `Sim` and a task, turn actions into batched commands
(`ActionMap`) and call the task once per control step through a `TaskRunner`.

Observations hold only what a copter could know on board (its sensors, see
`SENSOR_OBS_COLUMNS`) plus task information, such as the goal's position relative to the
copter. That relative position is computed from ground truth, as the lab's tracking system
would provide it; so is everything a task scores. `truth_obs=True` appends the copter's own
true position and velocity: a development aid, like the `target` flight mode, not something
a real FINken knows.

The interface of a task, all arrays over the sim's n copters in id order:

- ``bind(sim, boxes)``: once, before the first episode (arena size, static boxes).
- ``reset(sim, rng)``: after every `Sim.reset`; may draw goals from `rng`.
- ``update(sim, prev_truth, truth, crashed)``: bookkeeping after every step (coverage).
- ``observe(sim) -> float32 (n, k)``, clipped to ``observation_bounds()``.
- ``reward(sim, prev_truth, truth, crashed) -> float (n,)``.
- ``done(sim) -> bool (n,)``: the task's own end of an episode (crashes end it anyway).
- ``info(sim) -> dict[str, (n,)]``: per-copter numbers for the step's info dicts.

`prev_truth` and `truth` are `Sim.truth()` before and after the step ((n, 14), columns
`twinswarm.TRUTH_COLUMNS`, the last one `crashed`); `crashed` is `Sim.crashed()` after it.
Every built-in reward gives a copter that crashed during the step `-crash_penalty` (once:
`prev_truth`'s crashed column is 0 and `crashed` is True) and a copter crashed before the
step 0.
"""
from __future__ import annotations

import copy
import math
from typing import Any, Callable, Mapping, Sequence

import numpy as np

# Column order of `Sim.truth()` and `Sim.sensors()`: the package's own definitions.
from twinswarm import SENSOR_COLUMNS, TRUTH_COLUMNS

_T = {name: i for i, name in enumerate(TRUTH_COLUMNS)}
_S = {name: i for i, name in enumerate(SENSOR_COLUMNS)}

# The on-board part of every observation: `Sim.sensors()` with the IR reading split into a
# distance (0 when out of range) and a validity flag. Units: m, rad, rad/s, m/s^2, V.
SENSOR_OBS_COLUMNS = (
    "sonar_front", "sonar_right", "sonar_back", "sonar_left", "ir", "ir_valid", "roll", "pitch",
    "yaw", "p", "q", "r", "ax", "ay", "az", "height_est", "battery_v", "battery_charge",
)
# Bounds the sensor columns are clipped to; (None, None) for height_est: set from the arena.
_SENSOR_BOUNDS = {
    "sonar_front": (0.0, 10.0), "sonar_right": (0.0, 10.0), "sonar_back": (0.0, 10.0),
    "sonar_left": (0.0, 10.0), "ir": (0.0, 5.0), "ir_valid": (0.0, 1.0),
    "roll": (-math.pi, math.pi), "pitch": (-math.pi, math.pi), "yaw": (-math.pi, math.pi),
    "p": (-20.0, 20.0), "q": (-20.0, 20.0), "r": (-20.0, 20.0),
    "ax": (-60.0, 60.0), "ay": (-60.0, 60.0), "az": (-60.0, 60.0),
    "height_est": (None, None), "battery_v": (0.0, 60.0), "battery_charge": (0.0, 1.0),
}
TRUTH_OBS_COLUMNS = ("x", "y", "z", "vx", "vy", "vz")
_SPEED_BOUND_M_S = 20.0


# ---- geometry helpers ----

def yaw_of(truth: np.ndarray) -> np.ndarray:
    """True heading (rad, counter-clockwise from +x) of each row of a truth array."""
    qx, qy, qz, qw = (truth[:, _T[c]].astype(np.float64) for c in ("qx", "qy", "qz", "qw"))
    return np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))


def to_heading_frame(truth: np.ndarray, rel_world: np.ndarray) -> np.ndarray:
    """World-frame offsets (n, 2 or 3) turned into each copter's heading frame: forward,
    left (and up, unchanged). The heading frame is the body frame without roll and pitch."""
    yaw = yaw_of(truth)
    c, s = np.cos(yaw), np.sin(yaw)
    out = np.array(rel_world, dtype=np.float64, copy=True)
    out[:, 0] = c * rel_world[:, 0] + s * rel_world[:, 1]
    out[:, 1] = -s * rel_world[:, 0] + c * rel_world[:, 1]
    return out


def newly_crashed(prev_truth: np.ndarray, crashed: np.ndarray) -> np.ndarray:
    """Copters that crashed during the step: crashed now, not crashed before it."""
    return np.asarray(crashed, dtype=bool) & (prev_truth[:, _T["crashed"]] < 0.5)


def crashed_before(prev_truth: np.ndarray) -> np.ndarray:
    return prev_truth[:, _T["crashed"]] >= 0.5


def sensor_features(sensors: np.ndarray) -> np.ndarray:
    """`Sim.sensors()` (n, 17) as the `SENSOR_OBS_COLUMNS` (n, 18), float64, not yet clipped."""
    n = sensors.shape[0]
    out = np.empty((n, len(SENSOR_OBS_COLUMNS)), dtype=np.float64)
    ir = sensors[:, _S["ir"]].astype(np.float64)
    valid = np.isfinite(ir)
    for j, name in enumerate(SENSOR_OBS_COLUMNS):
        if name == "ir":
            out[:, j] = np.where(valid, ir, 0.0)
        elif name == "ir_valid":
            out[:, j] = valid
        else:
            out[:, j] = sensors[:, _S[name]]
    return out


class StaticBox:
    """A static box of the scene: centre (x, y, z), half extents, yaw (from `Sim.boxes`)."""

    def __init__(self, center_m: Sequence[float], half_extents_m: Sequence[float], yaw_rad: float = 0.0):
        self.center_m = tuple(float(v) for v in center_m)
        self.half_m = tuple(float(v) for v in half_extents_m)
        self.yaw_rad = float(yaw_rad)

    def contains(self, p: np.ndarray, margin_m: float = 0.0) -> bool:
        """Whether the point p = (x, y, z) lies inside the box grown by `margin_m`."""
        dx, dy = p[0] - self.center_m[0], p[1] - self.center_m[1]
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        lx, ly = c * dx + s * dy, -s * dx + c * dy
        return (abs(lx) <= self.half_m[0] + margin_m and abs(ly) <= self.half_m[1] + margin_m
                and abs(p[2] - self.center_m[2]) <= self.half_m[2] + margin_m)


def sim_boxes(sim: Any) -> list[StaticBox]:
    """The static boxes of `sim`, as its engine has them (`Sim.boxes`)."""
    return [StaticBox(b["center_m"], b["half_extents_m"], b["yaw_rad"]) for b in sim.boxes]


# ---- tasks ----

class Task:
    """Base class of tasks; see the module docstring for the interface.

    The observation is `SENSOR_OBS_COLUMNS`, then the task's own columns (`task_columns`),
    then, with `truth_obs=True`, `TRUTH_OBS_COLUMNS` (true position m and velocity m/s,
    world frame: a development aid). Every column is clipped to `observation_bounds()`.
    Subclasses override `task_columns`, `task_bounds`, `task_features`, `reset`, `reward`
    and, when they need them, `update`, `done` and `info`.
    """

    name = "task"
    task_columns: tuple[str, ...] = ()

    def __init__(self, *, crash_penalty: float = 10.0, truth_obs: bool = False):
        if not math.isfinite(crash_penalty):
            raise ValueError(f"crash_penalty must be finite, got {crash_penalty}")
        self.crash_penalty = float(crash_penalty)
        self.truth_obs = bool(truth_obs)
        self.n = 0
        self.arena_size_m = (0.0, 0.0)
        self.arena_height_m = 0.0
        self.boxes: list[StaticBox] = []
        self._bounds: tuple[np.ndarray, np.ndarray] | None = None

    def __repr__(self) -> str:
        return f"{type(self).__name__}(crash_penalty={self.crash_penalty}, truth_obs={self.truth_obs})"

    # -- set-up --
    def bind(self, sim: Any, boxes: Sequence[StaticBox] = ()) -> None:
        """Learns the world: number of copters, arena, static boxes. Called once."""
        self.n = int(sim.n)
        sx, sy = sim.arena_size_m
        self.arena_size_m = (float(sx), float(sy))
        self.arena_height_m = float(sim.arena_height_m)
        self.boxes = list(boxes)
        self._bounds = None

    @property
    def observation_columns(self) -> tuple[str, ...]:
        return SENSOR_OBS_COLUMNS + tuple(self.task_columns) + (TRUTH_OBS_COLUMNS if self.truth_obs else ())

    def task_bounds(self) -> tuple[Sequence[float], Sequence[float]]:
        return (), ()

    def observation_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(low, high), float32 (k,), of the observation columns (after `bind`)."""
        lo, hi = [], []
        for name in SENSOR_OBS_COLUMNS:
            a, b = _SENSOR_BOUNDS[name]
            if name == "height_est":
                a, b = -1.0, self.arena_height_m + 1.0
            lo.append(a)
            hi.append(b)
        tlo, thi = self.task_bounds()
        lo += list(tlo)
        hi += list(thi)
        if self.truth_obs:
            sx, sy = self.arena_size_m
            lo += [-sx / 2 - 1.0, -sy / 2 - 1.0, -1.0] + [-_SPEED_BOUND_M_S] * 3
            hi += [sx / 2 + 1.0, sy / 2 + 1.0, self.arena_height_m + 1.0] + [_SPEED_BOUND_M_S] * 3
        return np.array(lo, dtype=np.float32), np.array(hi, dtype=np.float32)

    @property
    def goal_bound_m(self) -> float:
        """The largest distance inside the arena, m: the bound of relative-goal columns."""
        return float(math.hypot(self.arena_size_m[0], self.arena_size_m[1], self.arena_height_m))

    # -- per episode and per step --
    def reset(self, sim: Any, rng: np.random.Generator) -> None:
        pass

    def update(self, sim: Any, prev_truth: np.ndarray, truth: np.ndarray, crashed: np.ndarray) -> None:
        pass

    def task_features(self, sim: Any, truth: np.ndarray) -> np.ndarray:
        return np.zeros((truth.shape[0], 0))

    def observe(self, sim: Any) -> np.ndarray:
        truth = np.asarray(sim.truth())
        parts = [sensor_features(np.asarray(sim.sensors())), self.task_features(sim, truth)]
        if self.truth_obs:
            parts.append(truth[:, [_T[c] for c in TRUTH_OBS_COLUMNS]])
        obs = np.nan_to_num(np.concatenate(parts, axis=1), nan=0.0)
        if self._bounds is None:
            self._bounds = self.observation_bounds()
        return np.clip(obs, *self._bounds).astype(np.float32)

    def reward(self, sim: Any, prev_truth: np.ndarray, truth: np.ndarray, crashed: np.ndarray) -> np.ndarray:
        raise NotImplementedError(f"{type(self).__name__} defines no reward")

    def done(self, sim: Any) -> np.ndarray:
        return np.zeros(self.n, dtype=bool)

    def info(self, sim: Any) -> dict[str, np.ndarray]:
        return {}

    def _crash_terms(self, prev_truth: np.ndarray, crashed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(penalty (n,), alive_before (n,)): -crash_penalty for a crash during the step."""
        return -self.crash_penalty * newly_crashed(prev_truth, crashed), ~crashed_before(prev_truth)


class _GoalTask(Task):
    """A task with one goal point per copter, observed as `goal_fwd, goal_left, goal_up`: the
    goal relative to the copter in its heading frame (m; task information, from ground truth)."""

    task_columns = ("goal_fwd", "goal_left", "goal_up")

    def __init__(self, **kw: Any):
        super().__init__(**kw)
        self.goals_m = np.zeros((0, 3))

    def task_bounds(self):
        b = self.goal_bound_m
        return [-b] * 3, [b] * 3

    def goal_distance(self, truth: np.ndarray) -> np.ndarray:
        return np.linalg.norm(truth[:, :3].astype(np.float64) - self.goals_m, axis=1)

    def task_features(self, sim, truth):
        return to_heading_frame(truth, self.goals_m - truth[:, :3].astype(np.float64))

    def info(self, sim):
        return {"goal_distance_m": self.goal_distance(np.asarray(sim.truth()))}


class HoverTask(_GoalTask):
    """Hover: each copter holds the point `height_m` (1 m) above its start position.

    Observation: `SENSOR_OBS_COLUMNS` + `goal_fwd, goal_left, goal_up`.
    Reward per copter and step, with d the distance to its point after the step (m):
    ``exp(-d / scale_m)`` (scale_m = 0.5 m; 1 on the point, 0.14 one metre off), minus
    `crash_penalty` (10) on the step of a crash, 0 after one. `done`: never (episodes end on a
    crash or at the step limit).
    """

    name = "hover"

    def __init__(self, *, height_m: float = 1.0, scale_m: float = 0.5, **kw: Any):
        super().__init__(**kw)
        if not (height_m > 0 and scale_m > 0):
            raise ValueError(f"height_m and scale_m must be positive, got {height_m}, {scale_m}")
        self.height_m = float(height_m)
        self.scale_m = float(scale_m)

    def reset(self, sim, rng):
        truth = np.asarray(sim.truth())
        self.goals_m = np.column_stack([truth[:, 0], truth[:, 1], np.full(self.n, self.height_m)]).astype(np.float64)

    def reward(self, sim, prev_truth, truth, crashed):
        penalty, alive = self._crash_terms(prev_truth, crashed)
        crashed = np.asarray(crashed, dtype=bool)
        flying = np.exp(-self.goal_distance(truth) / self.scale_m)
        return np.where(alive, np.where(crashed, 0.0, flying) + penalty, 0.0)


class ReachTask(_GoalTask):
    """Reach a target: each copter gets a random target point and must fly to it.

    Targets are drawn at every reset, uniformly in the arena `margin_m` (0.4 m) from the walls,
    `z_range_m` (0.5 to 1.8 m, at most 0.5 m below the ceiling) high, outside every box grown by
    `margin_m`, and at least `min_separation_m` (0.6 m) from every start and every other target.
    Observation: `SENSOR_OBS_COLUMNS` + `goal_fwd, goal_left, goal_up`.
    Reward per copter and step, with d_prev and d the distances to the target before and after
    the step (m): ``(d_prev - d)`` (progress), plus `arrival_bonus` (10) on the step it comes
    within `arrival_radius_m` (0.2 m), minus `crash_penalty` (10) on the step of a crash, 0
    after one. `done`: within `arrival_radius_m` of the target (the agent's episode ends; its
    copter hovers where it is).
    """

    name = "reach"

    def __init__(self, *, arrival_radius_m: float = 0.2, arrival_bonus: float = 10.0, margin_m: float = 0.4,
                 z_range_m: tuple[float, float] = (0.5, 1.8), min_separation_m: float = 0.6, **kw: Any):
        super().__init__(**kw)
        if not arrival_radius_m > 0:
            raise ValueError(f"arrival_radius_m must be positive, got {arrival_radius_m}")
        self.arrival_radius_m = float(arrival_radius_m)
        self.arrival_bonus = float(arrival_bonus)
        self.margin_m = float(margin_m)
        self.z_range_m = (float(z_range_m[0]), float(z_range_m[1]))
        self.min_separation_m = float(min_separation_m)

    def _free(self, p: np.ndarray, taken: list[np.ndarray]) -> bool:
        if any(b.contains(p, self.margin_m) for b in self.boxes):
            return False
        return all(np.hypot(p[0] - q[0], p[1] - q[1]) >= self.min_separation_m for q in taken)

    def reset(self, sim, rng):
        truth = np.asarray(sim.truth())
        sx, sy = self.arena_size_m
        hx, hy = max(sx / 2 - self.margin_m, 0.0), max(sy / 2 - self.margin_m, 0.0)
        z_hi = min(self.z_range_m[1], self.arena_height_m - 0.5)
        z_lo = min(self.z_range_m[0], z_hi)
        taken = [truth[i, :2].astype(np.float64) for i in range(self.n)]
        goals = []
        for _ in range(self.n):
            for _attempt in range(1000):  # a crowded arena keeps the last draw
                p = np.array([rng.uniform(-hx, hx), rng.uniform(-hy, hy), rng.uniform(z_lo, z_hi)])
                if self._free(p, taken):
                    break
            goals.append(p)
            taken.append(p)
        self.goals_m = np.array(goals, dtype=np.float64).reshape(self.n, 3)

    def reward(self, sim, prev_truth, truth, crashed):
        penalty, alive = self._crash_terms(prev_truth, crashed)
        d_prev, d = self.goal_distance(prev_truth), self.goal_distance(truth)
        arrived = (d < self.arrival_radius_m) & (d_prev >= self.arrival_radius_m) & ~np.asarray(crashed, dtype=bool)
        return np.where(alive, (d_prev - d) + self.arrival_bonus * arrived + penalty, 0.0)

    def done(self, sim):
        return self.goal_distance(np.asarray(sim.truth())) < self.arrival_radius_m


class CoverageTask(Task):
    """Area coverage: the swarm visits the cells of a grid over the arena floor.

    The floor is tiled exactly by cells of about `cell_m` (0.5 m). A cell is covered once a
    copter that has not crashed is above it at `min_height_m` (0.3 m) or higher.
    Observation: `SENSOR_OBS_COLUMNS` + `uncovered_fwd, uncovered_left` (the centre of the
    nearest uncovered cell relative to the copter, m, heading frame, from ground truth; 0 when
    all are covered) + `covered_fraction` (of all cells, shared by the swarm).
    Reward per copter and step: ``N_new`` (the number of cells the whole swarm covered for the
    first time during the step: a shared reward, 1 per cell), minus `crash_penalty` (10) on the
    step of a crash, 0 after one. `done`: every cell covered (all copters' episodes end).
    """

    name = "coverage"
    task_columns = ("uncovered_fwd", "uncovered_left", "covered_fraction")

    def __init__(self, *, cell_m: float = 0.5, min_height_m: float = 0.3, **kw: Any):
        super().__init__(**kw)
        if not cell_m > 0:
            raise ValueError(f"cell_m must be positive, got {cell_m}")
        self.cell_m = float(cell_m)
        self.min_height_m = float(min_height_m)
        self.covered = np.zeros((0, 0), dtype=bool)
        self.new_cells = 0

    def bind(self, sim, boxes=()):
        super().bind(sim, boxes)
        sx, sy = self.arena_size_m
        self.shape = (max(1, math.ceil(sx / self.cell_m - 1e-9)), max(1, math.ceil(sy / self.cell_m - 1e-9)))
        self.cell_size_m = (sx / self.shape[0], sy / self.shape[1])
        ix, iy = np.meshgrid(np.arange(self.shape[0]), np.arange(self.shape[1]), indexing="ij")
        self.centres_m = np.column_stack([-sx / 2 + (ix.ravel() + 0.5) * self.cell_size_m[0],
                                          -sy / 2 + (iy.ravel() + 0.5) * self.cell_size_m[1]])
        self.covered = np.zeros(self.shape, dtype=bool)

    def task_bounds(self):
        b = float(math.hypot(*self.arena_size_m))
        return [-b, -b, 0.0], [b, b, 1.0]

    def reset(self, sim, rng):
        self.covered = np.zeros(self.shape, dtype=bool)
        self.new_cells = 0
        self.update(sim, None, np.asarray(sim.truth()), np.asarray(sim.crashed()))
        self.new_cells = 0

    def update(self, sim, prev_truth, truth, crashed):
        sx, sy = self.arena_size_m
        ok = ~np.asarray(crashed, dtype=bool) & (truth[:, 2] >= self.min_height_m)
        ix = np.clip(((truth[ok, 0] + sx / 2) / self.cell_size_m[0]).astype(int), 0, self.shape[0] - 1)
        iy = np.clip(((truth[ok, 1] + sy / 2) / self.cell_size_m[1]).astype(int), 0, self.shape[1] - 1)
        before = int(self.covered.sum())
        self.covered[ix, iy] = True
        self.new_cells = int(self.covered.sum()) - before

    @property
    def covered_fraction(self) -> float:
        return float(self.covered.mean())

    def task_features(self, sim, truth):
        n = truth.shape[0]
        out = np.zeros((n, 3))
        out[:, 2] = self.covered_fraction
        open_cells = self.centres_m[~self.covered.ravel()]
        if len(open_cells):
            rel = open_cells[None, :, :] - truth[:, None, :2].astype(np.float64)
            nearest = rel[np.arange(n), np.argmin((rel ** 2).sum(axis=2), axis=1)]
            out[:, :2] = to_heading_frame(truth, nearest)
        return out

    def reward(self, sim, prev_truth, truth, crashed):
        penalty, alive = self._crash_terms(prev_truth, crashed)
        return np.where(alive, float(self.new_cells) + penalty, 0.0)

    def done(self, sim):
        return np.full(self.n, bool(self.covered.all()))

    def info(self, sim):
        return {"covered_fraction": np.full(self.n, self.covered_fraction)}


TASKS: dict[str, type[Task]] = {"hover": HoverTask, "reach": ReachTask, "coverage": CoverageTask}

RewardFn = Callable[[Any, np.ndarray, np.ndarray, np.ndarray], Any]


def make_task(task: str | Task) -> Task:
    """A fresh task from a name of `TASKS`, or a deep copy of a Task instance (each
    environment keeps its own goals and grid)."""
    if isinstance(task, Task):
        return copy.deepcopy(task)
    if isinstance(task, str):
        if task not in TASKS:
            raise ValueError(f"task: unknown task {task!r}; known: {sorted(TASKS)} (or pass a twinswarm.tasks.Task)")
        return TASKS[task]()
    raise TypeError(f"task: expected a task name or a twinswarm.tasks.Task, got {type(task).__name__}")


# ---- actions ----

class ActionMap:
    """Turns normalised actions in [-1, 1]^4 into batched `Sim.command` calls.

    `kind="velocity"` (flight mode `velocity`): a = (forward, left, height, yaw rate):
    forward and left speed ``a * max_speed_m_s`` (1 m/s, body frame, open loop), height
    ``lo + (a + 1) / 2 * (hi - lo)`` with (lo, hi) = `height_band_m` (0.3 m to 2 m, at most
    0.4 m below the ceiling), yaw rate ``a * yaw_rate_rad_s`` (1 rad/s) integrated into the
    yaw command from the copter's heading at reset.
    `kind="rotors"` (flight mode `rotors`): the four rotor commands ``(a + 1) / 2`` in [0, 1]
    (front-left, front-right, back-right, back-left), no attitude or height loop.
    Actions outside [-1, 1] are clipped; NaN or infinite ones raise ValueError.
    """

    KINDS = ("velocity", "rotors")

    def __init__(self, kind: str, sim: Any, *, max_speed_m_s: float = 1.0,
                 height_band_m: tuple[float, float] | None = None, yaw_rate_rad_s: float = 1.0):
        if kind not in self.KINDS:
            raise ValueError(f"action: unknown action kind {kind!r}; known: {list(self.KINDS)}")
        self.kind = kind
        self.max_speed_m_s = float(max_speed_m_s)
        self.yaw_rate_rad_s = float(yaw_rate_rad_s)
        ceiling = float(sim.arena_height_m)
        lo, hi = height_band_m if height_band_m is not None else (0.3, min(2.0, ceiling - 0.4))
        if not 0 < lo < hi:
            raise ValueError(f"height_band_m: need 0 < low < high, got ({lo}, {hi}) (arena {ceiling} m high)")
        self.height_band_m = (float(lo), float(hi))
        self.dt_s = float(sim.dt)
        self.yaw_cmd_rad = np.zeros(int(sim.n))
        self.height_cmd_m = np.zeros(int(sim.n))

    def reset(self, sim: Any) -> None:
        truth = np.asarray(sim.truth())
        self.yaw_cmd_rad = yaw_of(truth)
        self.height_cmd_m = np.clip(truth[:, 2].astype(np.float64), *self.height_band_m)
        sim.command("mode", self.kind)

    def command(self, sim: Any, actions: np.ndarray, ids: Sequence[int]) -> None:
        """Sends `actions` (len(ids), 4) for the copters `ids` (validated by the caller)."""
        if len(ids) == 0:
            return
        a = np.clip(actions, -1.0, 1.0)
        ids = list(ids)
        if self.kind == "velocity":
            lo, hi = self.height_band_m
            yaw = self.yaw_cmd_rad[ids] + a[:, 3] * self.yaw_rate_rad_s * self.dt_s
            yaw = (yaw + math.pi) % (2 * math.pi) - math.pi
            self.yaw_cmd_rad[ids] = yaw
            self.height_cmd_m[ids] = lo + (a[:, 2] + 1.0) / 2.0 * (hi - lo)
            cmd = np.column_stack([a[:, 0] * self.max_speed_m_s, a[:, 1] * self.max_speed_m_s,
                                   self.height_cmd_m[ids], yaw])
            sim.command("velocity", cmd.astype(np.float64), ids=ids)
        else:
            sim.command("rotors", ((a + 1.0) / 2.0).astype(np.float64), ids=ids)

    def hold(self, sim: Any, ids: Sequence[int]) -> None:
        """Leaves the copters `ids` hovering where they are: velocity mode, zero speed, at
        their present height (within the band) and heading. For agents whose episode ended
        without a crash while the others fly on."""
        if len(ids) == 0:
            return
        ids = list(ids)
        truth = np.asarray(sim.truth())[ids]
        z = np.clip(truth[:, 2].astype(np.float64), *self.height_band_m)
        sim.command("mode", "velocity", ids=ids)
        sim.command("velocity", np.column_stack([np.zeros(len(ids)), np.zeros(len(ids)), z, yaw_of(truth)]), ids=ids)


def check_actions(actions: Any, rows: int, who: Callable[[int], str]) -> np.ndarray:
    """`actions` as a float64 (rows, 4) array, or ValueError/TypeError naming the culprit."""
    try:
        a = np.asarray(actions, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise TypeError(f"action: expected numbers, got {type(actions).__name__}: {e}") from None
    if rows == 1 and a.shape == (4,):
        a = a.reshape(1, 4)
    if a.shape != (rows, 4):
        raise ValueError(f"action: expected shape ({rows}, 4) (or (4,) for one copter), got {a.shape}")
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
        raise ValueError(f"action for {who(int(np.argmax(bad)))}: NaN or infinite: {a[bad][0].tolist()}")
    return a


# ---- the runner the environments share ----

class TaskRunner:
    """One Sim, one task, one action map: the step logic of every environment.

    The environment calls `reset`, then per step `act` (commands), steps the sim (itself or
    with `twinswarm.step_many`) and calls `collect`.
    """

    def __init__(self, sim: Any, task: str | Task, *, scene: Any = None, action: str = "velocity",
                 reward_fn: RewardFn | None = None, max_steps: int = 500):
        if isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
            raise ValueError(f"max_steps: expected a positive integer, got {max_steps!r}")
        if reward_fn is not None and not callable(reward_fn):
            raise TypeError(f"reward_fn: expected a callable (sim, prev_truth, truth, crashed) -> (n,), "
                            f"got {type(reward_fn).__name__}")
        self.sim = sim
        self.task = make_task(task)
        self.task.bind(sim, sim_boxes(sim))
        self.actions = ActionMap(action, sim)
        self.reward_fn = reward_fn
        self.max_steps = int(max_steps)
        self.steps = 0
        self.names = list(sim.names)
        self.n = len(self.names)
        self.truth = np.asarray(sim.truth())
        low, high = self.task.observation_bounds()
        self.obs_low, self.obs_high = low, high

    @property
    def truncated(self) -> bool:
        return self.steps >= self.max_steps

    def reset(self, sim_seed: int, rng: np.random.Generator) -> np.ndarray:
        """Sim back to its start with `sim_seed`; task goals from `rng`. Returns obs (n, k)."""
        self.sim.reset(seed=int(sim_seed))
        self.steps = 0
        self.task.reset(self.sim, rng)
        self.actions.reset(self.sim)
        self.truth = np.asarray(self.sim.truth())
        return self.task.observe(self.sim)

    def act(self, actions: np.ndarray, ids: Sequence[int]) -> None:
        self.actions.command(self.sim, actions, ids)

    def collect(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """After a step: (obs (n, k), reward float64 (n,), crashed (n,), terminated (n,), info)."""
        self.steps += 1
        prev, truth = self.truth, np.asarray(self.sim.truth())
        crashed = np.asarray(self.sim.crashed(), dtype=bool)
        self.truth = truth
        self.task.update(self.sim, prev, truth, crashed)
        if self.reward_fn is None:
            reward = self.task.reward(self.sim, prev, truth, crashed)
        else:
            reward = self.reward_fn(self.sim, prev.copy(), truth.copy(), crashed.copy())
        reward = self._check_reward(reward)
        terminated = crashed | np.asarray(self.task.done(self.sim), dtype=bool)
        info = {"crashed": crashed, **self.task.info(self.sim)}
        return self.task.observe(self.sim), reward, crashed, terminated, info

    def _check_reward(self, reward: Any) -> np.ndarray:
        source = "reward_fn" if self.reward_fn is not None else f"{type(self.task).__name__}.reward"
        try:
            r = np.asarray(reward, dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise TypeError(f"{source}: expected numbers, one per copter, got {type(reward).__name__}: {e}") from None
        if r.shape == () and self.n == 1:
            r = r.reshape(1)
        if r.shape != (self.n,):
            raise ValueError(f"{source}: expected shape ({self.n},), one reward per copter, got {r.shape}")
        bad = ~np.isfinite(r)
        if bad.any():
            raise ValueError(f"{source}: reward for {self.names[int(np.argmax(bad))]} is {r[bad][0]}")
        return r

    def render_text(self) -> str:
        truth = self.truth
        lines = [f"t = {self.sim.time_s:.2f} s (step {self.steps}/{self.max_steps})"]
        for i, name in enumerate(self.names):
            state = "crashed" if truth[i, _T["crashed"]] >= 0.5 else ""
            lines.append(f"  {name:>10}  x {truth[i, 0]:+6.2f}  y {truth[i, 1]:+6.2f}  z {truth[i, 2]:5.2f} m  {state}")
        return "\n".join(lines) + "\n"


def info_rows(info: Mapping[str, np.ndarray], i: int) -> dict[str, Any]:
    """Copter `i`'s entries of a runner's info, as Python scalars."""
    return {k: v[i].item() for k, v in info.items()}
