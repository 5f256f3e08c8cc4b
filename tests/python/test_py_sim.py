"""The Python package `twinswarm` (crates/py) against the CLI it shares its engine with.

- the README's quick start flies the lab;
- a Python run's digests equal `twinswarm run --json`'s for the same scene and seed, with the
  scene's own commands and with commands written from Python (the same numbers as a Zenoh
  client would send; the lockstep test checks that path);
- snapshot and restore are bit-exact;
- every command kind flies, and bad input raises an exception that names what and where;
- `log=` writes an MCAP log that PyPI `mcap` reads with its CRCs checked.
"""
import json
import subprocess

import numpy as np
import pytest

import twinswarm
from conftest import ROOT


def cli_digests(twinswarm_bin, *args):
    out = subprocess.run([str(twinswarm_bin), "run", "--no-bus", "--no-log", "--json", *args],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout)
    return summary, [c["digest"] for c in summary["copters"]]


def test_readme_quick_start_flies_the_lab():
    sim = twinswarm.Sim()
    sim.step(200)
    truth = sim.truth()
    assert sim.n == 2 and sim.names == ["finken1", "finken2"]
    assert truth.shape == (2, len(twinswarm.TRUTH_COLUMNS)) and truth.dtype == np.float32
    assert sim.tick == 200 and abs(sim.time_s - 10.0) < 1e-9
    z = truth[:, twinswarm.TRUTH_COLUMNS.index("z")]
    assert np.all(np.abs(z - 0.8) < 0.25), f"the lab's copters hover near 0.8 m: {z}"
    sensors = sim.sensors()
    assert sensors.shape == (2, len(twinswarm.SENSOR_COLUMNS))
    sonar = sensors[:, :4]
    assert np.all((sonar > 0.0) & (sonar < 5.0)), sonar


def test_digests_equal_the_clis_for_the_same_scene_and_seed(twinswarm_bin):
    summary, digests = cli_digests(twinswarm_bin, "--duration", "10", "--seed", "7")
    sim = twinswarm.Sim(seed=7)
    sim.step(summary["control_steps"])
    assert sim.digest() == digests


def test_digests_equal_the_clis_on_a_generated_swarm_on_two_threads(twinswarm_bin, tmp_path):
    scene = subprocess.run([str(twinswarm_bin), "scene", "dense", "--n", "30"], capture_output=True, text=True,
                           check=True).stdout
    path = tmp_path / "dense.toml"
    path.write_text(scene)
    summary, digests = cli_digests(twinswarm_bin, str(path), "--duration", "5", "--threads", "2")
    sim = twinswarm.Sim(scene=scene, threads=2)  # TOML text this time
    sim.step(summary["control_steps"])
    assert sim.digest() == digests
    assert int(sim.crashed().sum()) == len(summary["crashes"])


def test_snapshot_and_restore_are_bit_exact():
    sim = twinswarm.Sim(seed=3)
    sim.step(60)
    snap = sim.snapshot()
    sim.command("velocity", [0.3, -0.1, 1.0, 0.2])
    sim.step(40)
    straight = (sim.digest(), sim.truth().tobytes(), sim.sensors().tobytes())
    sim.restore(snap)
    assert sim.tick == 60
    sim.command("velocity", [0.3, -0.1, 1.0, 0.2])
    sim.step(40)
    assert (sim.digest(), sim.truth().tobytes(), sim.sensors().tobytes()) == straight
    other = twinswarm.Sim(seed=3)
    other.restore(snap)
    other.command("velocity", [0.3, -0.1, 1.0, 0.2])
    other.step(40)
    assert other.digest() == straight[0], "a snapshot restores into another Sim of the scene"


def test_reset_replays_and_a_new_seed_differs():
    sim = twinswarm.Sim()
    sim.step(100)
    first = sim.digest()
    sim.reset()
    assert sim.tick == 0
    sim.step(100)
    assert sim.digest() == first
    sim.reset(seed=99)
    sim.step(100)
    assert sim.digest() != first and sim.seed == 99


def test_every_command_kind_flies():
    sim = twinswarm.Sim()
    # Open loop, with no position hold: an untrimmed copter drifts (0.25 m/s here) and would
    # reach a wall after some 6 s, so the check comes at 2.5 s.
    sim.command("velocity", [[0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    sim.step(50)
    assert np.all(np.abs(sim.truth()[:, 2] - 1.0) < 0.2), "velocity: both climb to 1 m"
    sim.command("attitude", [0.0, 0.0, 0.0, 0.0], ids=1)
    sim.step(5)
    assert sim.truth()[1, 5] < -0.5, "attitude with no thrust: it falls"

    sim = twinswarm.Sim()
    sim.command("rotors", [0.0, 0.0, 0.0, 0.0], ids=["finken2"])  # stays on the floor
    sim.command("target", [0.0, 0.5, 1.0], ids=["finken1"])
    sim.step(300)
    t = sim.truth()
    assert not sim.crashed().any()
    assert abs(t[0, 0]) < 0.25 and abs(t[0, 1] - 0.5) < 0.25 and abs(t[0, 2] - 1.0) < 0.15, t[0, :3]
    assert t[1, 2] < 0.1, "rotors at zero: on the floor"
    sim.command("rotors", [0.6, 0.6, 0.6, 0.6], ids=["finken2"])
    sim.step(10)
    assert sim.truth()[1, 5] > 0.5, "rotors at 60 %: it climbs"
    sim.command("mode", ["wall_avoid", "wall_avoid"])


def test_bad_input_raises_clear_errors(tmp_path):
    sim = twinswarm.Sim()
    with pytest.raises(ValueError, match=r"expected shape \(2, 4\).*forward, left, height, yaw.*got \(2, 3\)"):
        sim.command("velocity", np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"row 1 \(copter 1, 'finken2'\) column 'height' is nan"):
        sim.command("velocity", [[0, 0, 1, 0], [0, 0, float("nan"), 0]])
    with pytest.raises(ValueError, match=r"unknown copter id 5 \(ids are 0 to 1\)"):
        sim.command("target", [0, 0, 1], ids=[5])
    with pytest.raises(ValueError, match=r"unknown copter 'nope'"):
        sim.command("target", [0, 0, 1], ids=["nope"])
    with pytest.raises(ValueError, match=r"unknown command kind 'fly'"):
        sim.command("fly", [0, 0, 1])
    with pytest.raises(ValueError, match=r"row 0 \(copter 0, \"finken1\"\).*`target` = 9 is out of range"):
        sim.command("target", [9, 0, 1], ids=[0])
    with pytest.raises(ValueError, match=r"`rotors` = 1.5 is out of range \[0, 1\]"):
        sim.command("rotors", [1.5, 0, 0, 0])
    with pytest.raises(ValueError, match=r"unknown mode 'loop'"):
        sim.command("mode", "loop")
    with pytest.raises(TypeError, match=r"steps: expected an int"):
        sim.step(1.5)
    with pytest.raises(ValueError, match=r"steps: -1 is out of range"):
        sim.step(-1)
    with pytest.raises(TypeError, match=r"expected the bytes of Sim.snapshot"):
        sim.restore("not bytes")
    with pytest.raises(ValueError, match=r"restore: not a snapshot"):
        sim.restore(b"\x01\x02")
    grid = twinswarm.Sim(scene=subprocess_scene(3))
    with pytest.raises(ValueError, match=r"restore: the snapshot has 3 copters, this Sim 2"):
        sim.restore(grid.snapshot())
    with pytest.raises(FileNotFoundError, match=r"no file 'missing.toml'"):
        twinswarm.Sim(scene="missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "x"\n[arena]\nsize_m = [4.0, -3.0]\nheight_m = 2.5\n')
    with pytest.raises(ValueError, match=r"scene: .*bad.toml.*size_m"):
        twinswarm.Sim(scene=bad)
    with pytest.raises(ValueError, match=r"threads: 0 is out of range"):
        twinswarm.Sim(threads=0)
    assert sim.tick == 0 and np.all(sim.truth()[:, 2] < 0.1), "nothing applied, nothing stepped"


def test_a_twin_refuses_commands():
    text = (ROOT / "assets" / "scenes" / "finken_lab.toml").read_text()
    text = text.replace('name = "finken2"\nkind = "virtual"', 'name = "finken2"\nkind = "real"')
    assert 'kind = "real"' in text
    sim = twinswarm.Sim(scene=text)
    assert sim.kinds == ["virtual", "twin"]
    with pytest.raises(ValueError, match=r"copter 1 \(\"finken2\"\) is a twin"):
        sim.command("velocity", np.zeros((2, 4)))
    sim.command("velocity", [0, 0, 1, 0], ids=[0])


def test_log_is_a_valid_mcap_and_the_live_view_serves(tmp_path):
    from mcap.reader import make_reader

    path = tmp_path / "py.mcap"
    with twinswarm.Sim(log=path, foxglove="127.0.0.1:0") as sim:
        assert sim.foxglove_address.startswith("127.0.0.1:")
        sim.step(100)
        with pytest.raises(RuntimeError, match="cannot be reset"):
            sim.reset()
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        counts = {}
        for _schema, channel, _message in reader.iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    # Two copters, 100 steps; a copter whose sample did not change may be held (not here:
    # they take off at once).
    assert counts["/copters/state"] == 200 and counts["/copters/sensors"] >= 100, counts


def test_step_many_equals_stepping_one_by_one():
    sims = [twinswarm.Sim(seed=s) for s in range(4)]
    twinswarm.step_many(sims, 50)
    alone = []
    for s in range(4):
        one = twinswarm.Sim(seed=s)
        one.step(50)
        alone.append(one.digest())
    assert [s.digest() for s in sims] == alone
    with pytest.raises(ValueError, match="appears twice"):
        twinswarm.step_many([sims[0], sims[0]])


def subprocess_scene(n):
    """A generated hover grid of `n` copters, as TOML (from the CLI's own generator)."""
    import os

    binary = os.environ.get("TWINSWARM_BIN", str(ROOT / "target" / "debug" / "twinswarm"))
    return subprocess.run([binary, "scene", "hover", "--n", str(n)], capture_output=True, text=True,
                          check=True).stdout
