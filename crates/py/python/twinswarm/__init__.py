"""Twinswarm in Python: a deterministic simulator for swarms of FINken indoor quadcopters.

    import twinswarm
    sim = twinswarm.Sim()              # the embedded lab: 2 copters, Wall-Avoid at 0.8 m
    sim.step(200)                      # 10 s, without the GIL
    print(sim.truth()[:, :3])          # positions, one numpy call for the whole swarm

The engine is the `twinswarm` CLI's (`run`): the same scene, seed and commands give the same
bits, and `Sim.digest()` equals the digests of `twinswarm run --json`.

Observations are numpy arrays of shape (n, k), one row per copter in id order, with the
columns named in `TRUTH_COLUMNS` and `SENSOR_COLUMNS`. Actions are batched:
`Sim.command(kind, array, ids=None)` with the kinds of `COMMAND_KINDS`, or "mode".
"""
from __future__ import annotations

import os
from typing import Iterable, Optional, Sequence, Union

import numpy as np

from . import _native

__all__ = [
    "Sim",
    "step_many",
    "TRUTH_COLUMNS",
    "SENSOR_COLUMNS",
    "COMMAND_KINDS",
    "MODES",
    "parallel_env",
    "vector_env",
]

#: Columns of `Sim.truth()`: position (m), velocity (m/s), orientation quaternion (world from
#: body), angular velocity (rad/s), all in the world frame (x along the arena's long side, y
#: across, z up, origin at the floor's centre); `crashed` is 0 or 1.
TRUTH_COLUMNS = ("x", "y", "z", "vx", "vy", "vz", "qx", "qy", "qz", "qw", "wx", "wy", "wz", "crashed")

#: Columns of `Sim.sensors()`: the four sonars as measured (noise, quantisation, cross-talk
#: from other copters' pings), m; the IR height, m (NaN out of range); the AHRS attitude
#: (roll, pitch, yaw with its drift), rad; gyro rates p, q, r (body), rad/s; accelerometer
#: ax, ay, az (body), m/s^2; the height estimate the copter holds, m; battery voltage, V, and
#: charge, 0 to 1. Sonars and IR update at the sonar rate, the rest every step; before the
#: first step every sensor reads 0 (nothing has been sensed yet, as in the CLI's tick 0).
SENSOR_COLUMNS = (
    "sonar_front", "sonar_right", "sonar_back", "sonar_left", "ir",
    "roll", "pitch", "yaw", "p", "q", "r", "ax", "ay", "az",
    "height_est", "battery_v", "battery_charge",
)

#: Batched command kinds and their columns (units: m, m/s, rad; thrust and rotors 0 to 1).
#: - velocity: flown open loop (the tilt whose steady state is that velocity, body frame),
#:   height and yaw held: mode "velocity";
#: - target: a point in the world, position PD from ground truth (a development aid): mode
#:   "target";
#: - attitude: roll and pitch targets, yaw, and collective thrust as throttle (0.5 about
#:   hover), no height hold: mode "manual";
#: - rotors: four rotor commands, fractions of the maximum thrust, straight to the motors
#:   (front-left, front-right, back-right, back-left): mode "rotors".
COMMAND_KINDS = {
    "velocity": ("forward", "left", "height", "yaw"),
    "target": ("x", "y", "z"),
    "attitude": ("roll", "pitch", "yaw", "thrust"),
    "rotors": ("front_left", "front_right", "back_right", "back_left"),
}

#: Flight modes for `Sim.command("mode", ...)`.
MODES = ("manual", "mixed_manual", "wall_avoid", "target", "velocity", "rotors")

SceneArg = Union[None, str, "os.PathLike[str]"]


def _scene_args(scene: SceneArg):
    """(path, text): a path-like or a string naming a file is a path; any other string is TOML."""
    if scene is None:
        return None, None
    if isinstance(scene, os.PathLike):
        return os.fspath(scene), None
    if not isinstance(scene, str):
        raise TypeError(f"scene: expected a path, TOML text or None, got {type(scene).__name__}")
    if "\n" in scene or "=" in scene:
        return None, scene
    if not os.path.isfile(scene):
        raise FileNotFoundError(f"scene: no file {scene!r} (pass TOML text, a path, or None for the lab)")
    return scene, None


def _int(name: str, value, lo: int, hi: Optional[int] = None) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name}: expected an int, got {type(value).__name__}")
    value = int(value)
    if value < lo or (hi is not None and value > hi):
        raise ValueError(f"{name}: {value} is out of range [{lo}, {hi if hi is not None else 'inf'}]")
    return value


class Sim:
    """One simulated swarm, stepped on demand.

    `scene` is a path, TOML text, or None for the embedded lab; `seed` overrides the scene's;
    `threads` steps one world on that many threads (the same bits for any count). `log` writes
    an MCAP log as `twinswarm run --log` does; `foxglove` serves the live view (Foxglove
    WebSocket) at an address such as "127.0.0.1:8765" ("127.0.0.1:0": any free port, see
    `foxglove_address`). A Sim that records cannot be reset or restored.
    """

    def __init__(self, scene: SceneArg = None, seed: Optional[int] = None, threads: int = 1,
                 log: Union[None, str, "os.PathLike[str]"] = None, foxglove: Optional[str] = None):
        path, text = _scene_args(scene)
        if seed is not None:
            seed = _int("seed", seed, 0, 2**64 - 1)
        threads = _int("threads", threads, 1, 256)
        if log is not None and not isinstance(log, (str, os.PathLike)):
            raise TypeError(f"log: expected a path, got {type(log).__name__}")
        if foxglove is not None and not isinstance(foxglove, str):
            raise TypeError(f"foxglove: expected an address string like '127.0.0.1:8765', got {type(foxglove).__name__}")
        self._sim = _native.Sim(path, text, seed, threads, os.fspath(log) if log is not None else None, foxglove)
        self.names = list(self._sim.names)
        self._ids = {name: i for i, name in enumerate(self.names)}
        self._all = list(range(len(self.names)))

    # -- what it is -------------------------------------------------------------------------
    @property
    def n(self) -> int:
        """Number of copters."""
        return self._sim.n

    @property
    def kinds(self) -> list:
        """"virtual" or "twin" per copter."""
        return list(self._sim.kinds)

    @property
    def tick(self) -> int:
        """Control steps done."""
        return self._sim.tick

    @property
    def time_s(self) -> float:
        """Simulated time, s."""
        return self._sim.time_s

    @property
    def dt(self) -> float:
        """The control step, s."""
        return self._sim.dt

    @property
    def seed(self) -> int:
        return self._sim.seed

    @property
    def threads(self) -> int:
        return self._sim.threads

    @property
    def boxes(self) -> list:
        """The static boxes: dicts of name, center_m (x, y, z), half_extents_m, yaw_rad and
        virtual_only (seen only by twins' virtual sonars)."""
        return [dict(name=n, center_m=c, half_extents_m=h, yaw_rad=y, virtual_only=v)
                for n, c, h, y, v in self._sim.boxes]

    @property
    def scene_toml(self) -> str:
        """The scene's TOML text as given (the embedded lab's file for `scene=None`)."""
        return self._sim.scene_toml

    @property
    def default_steps(self) -> int:
        """Control steps in the scene's duration (what `twinswarm run` flies)."""
        return self._sim.default_steps

    @property
    def arena_size_m(self) -> tuple:
        return tuple(self._sim.arena_size_m)

    @property
    def arena_height_m(self) -> float:
        return self._sim.arena_height_m

    @property
    def foxglove_address(self) -> Optional[str]:
        return self._sim.foxglove_address

    @property
    def log_path(self) -> Optional[str]:
        p = self._sim.log_path
        return None if p is None else os.fspath(p)

    # -- stepping ---------------------------------------------------------------------------
    def reset(self, seed: Optional[int] = None) -> None:
        """Back to tick 0 (with a new seed if given)."""
        if seed is not None:
            seed = _int("seed", seed, 0, 2**64 - 1)
        self._sim.reset(seed)

    def step(self, steps: int = 1) -> None:
        """Runs `steps` control steps; the GIL is released meanwhile."""
        self._sim.step(_int("steps", steps, 0))

    # -- observations -----------------------------------------------------------------------
    def truth(self) -> np.ndarray:
        """Ground truth, float32 (n, 14): see `TRUTH_COLUMNS`."""
        return np.frombuffer(self._sim.truth(), dtype="<f4").reshape(self.n, len(TRUTH_COLUMNS))

    def sensors(self) -> np.ndarray:
        """What the copters sense, float32 (n, 17): see `SENSOR_COLUMNS`."""
        return np.frombuffer(self._sim.sensors(), dtype="<f4").reshape(self.n, len(SENSOR_COLUMNS))

    def crashed(self) -> np.ndarray:
        """bool (n,)."""
        return self.truth()[:, TRUTH_COLUMNS.index("crashed")] > 0.5

    def digest(self) -> list:
        """Each copter's digest (16 hex digits), as `twinswarm run --json` prints it."""
        return list(self._sim.digest())

    # -- actions ----------------------------------------------------------------------------
    def ids(self, ids: Union[None, int, str, Iterable[Union[int, str]]] = None) -> list:
        """Copter ids from ids or names (None: all)."""
        if ids is None:
            return list(self._all)
        if isinstance(ids, (str, int, np.integer)):
            ids = [ids]
        out = []
        for k in ids:
            if isinstance(k, str):
                if k not in self._ids:
                    raise ValueError(f"unknown copter {k!r} (copters: {', '.join(self.names[:8])}{', ...' if self.n > 8 else ''})")
                out.append(self._ids[k])
            elif isinstance(k, (int, np.integer)) and not isinstance(k, bool):
                if not 0 <= int(k) < self.n:
                    raise ValueError(f"unknown copter id {int(k)} (ids are 0 to {self.n - 1})")
                out.append(int(k))
            else:
                raise TypeError(f"ids: expected copter ids (int) or names (str), got {type(k).__name__}")
        if len(set(out)) != len(out):
            raise ValueError("ids: a copter appears twice")
        return out

    def command(self, kind: str, array, ids=None) -> None:
        """Commands of one kind for copters `ids` (default: all), one row each.

        Kinds and columns: `COMMAND_KINDS`; "mode" takes a mode name or one per copter. A 1-D
        array of the kind's width is one row, for one copter or broadcast to all of `ids`.
        Nothing applies unless every row is valid: a wrong shape, NaN, a value out of range,
        an unknown id or kind, or a twin (driven by its real copter) raises, naming the row.
        """
        if not isinstance(kind, str):
            raise TypeError(f"command kind: expected a string, got {type(kind).__name__}")
        rows = self._all if ids is None else self.ids(ids)
        if kind == "mode":
            modes = [array] if isinstance(array, str) else list(array)
            if len(modes) != len(rows) and len(modes) != 1:
                raise ValueError(f"command('mode'): {len(modes)} modes for {len(rows)} copters")
            unknown = set(modes).difference(MODES)
            if unknown:
                raise ValueError(f"command('mode'): unknown mode {sorted(unknown)[0]!r} (one of {', '.join(MODES)})")
            self._sim.command_mode(modes, rows)
            return
        if kind not in COMMAND_KINDS:
            raise ValueError(f"unknown command kind {kind!r} (one of {', '.join(COMMAND_KINDS)}, mode)")
        cols = COMMAND_KINDS[kind]
        try:
            a = np.asarray(array, dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise TypeError(f"command({kind!r}): expected numbers shaped (n, {len(cols)}): {e}") from None
        if a.ndim == 1 and a.shape[0] == len(cols):
            a = np.broadcast_to(a, (len(rows), len(cols)))
        if a.shape != (len(rows), len(cols)):
            raise ValueError(
                f"command({kind!r}): expected shape ({len(rows)}, {len(cols)}) with columns "
                f"[{', '.join(cols)}], got {a.shape}")
        bad = ~np.isfinite(a)
        if bad.any():
            r, c = (int(v) for v in np.argwhere(bad)[0])
            raise ValueError(
                f"command({kind!r}): row {r} (copter {rows[r]}, {self.names[rows[r]]!r}) column "
                f"{cols[c]!r} is {a[r, c]}, not a finite number")
        self._sim.command(kind, np.ascontiguousarray(a, dtype="<f8").tobytes(), len(cols), rows)

    # -- state ------------------------------------------------------------------------------
    def snapshot(self) -> bytes:
        """The whole state and the commands, bit-exact."""
        return self._sim.snapshot()

    def restore(self, snap: bytes) -> None:
        """Back to a snapshot of this scene; stepping on gives the same bits as before."""
        if not isinstance(snap, (bytes, bytearray, memoryview)):
            raise TypeError(f"restore: expected the bytes of Sim.snapshot(), got {type(snap).__name__}")
        self._sim.restore(bytes(snap))

    def close(self) -> None:
        """Finishes the log and stops the live view (also done when the Sim is collected)."""
        self._sim.close()

    def __getstate__(self) -> dict:
        """A Sim pickles as its scene, seed, threads and snapshot (for process-based vector
        environments); one that records does not pickle."""
        if self.log_path is not None or self.foxglove_address is not None:
            raise TypeError("a Sim that logs or serves the live view cannot be pickled")
        return {"scene": self.scene_toml, "seed": self.seed, "threads": self.threads, "snapshot": self.snapshot()}

    def __setstate__(self, state: dict) -> None:
        self.__init__(scene=state["scene"], seed=state["seed"], threads=state["threads"])
        self.restore(state["snapshot"])

    def __enter__(self) -> "Sim":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"twinswarm.Sim(n={self.n}, tick={self.tick}, time_s={self.time_s:.2f}, seed={self.seed})"


def step_many(sims: Sequence[Sim], steps: int = 1) -> None:
    """Steps independent Sims side by side on threads (the GIL released)."""
    sims = list(sims)
    for s in sims:
        if not isinstance(s, Sim):
            raise TypeError(f"step_many: expected twinswarm.Sim objects, got {type(s).__name__}")
    if len({id(s) for s in sims}) != len(sims):
        raise ValueError("step_many: a Sim appears twice")
    _native.step_many([s._sim for s in sims], _int("steps", steps, 0))


def parallel_env(**kwargs):
    """A PettingZoo ParallelEnv (see `twinswarm.pettingzoo_env.parallel_env`)."""
    from .pettingzoo_env import parallel_env as make

    return make(**kwargs)


def vector_env(num_envs: int = 8, **kwargs):
    """A Gymnasium VectorEnv of independent worlds stepped on threads (see
    `twinswarm.gym_env.TwinswarmVectorEnv`)."""
    from .gym_env import TwinswarmVectorEnv

    return TwinswarmVectorEnv(num_envs=num_envs, **kwargs)


def _register_gymnasium_envs() -> None:
    """gymnasium.make("twinswarm/Hover-v0") once twinswarm is imported, if gymnasium is there
    (the environments are optional: pip install "twinswarm[envs]")."""
    import importlib.util

    if importlib.util.find_spec("gymnasium") is not None:
        from .gym_env import register_envs

        register_envs()


_register_gymnasium_envs()

