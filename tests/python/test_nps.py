"""Paparazzi's own rotorcraft autopilot in the loop: NPS FINken aircraft (paparazzi/, built
against the Paparazzi tree of ../shared/paparazzi) flown by `twinswarm run` as copters of kind
`autopilot`, in lockstep over TCP (docs/paparazzi.md). Through scripts/nps_swarm.py, which
builds the aircraft, writes the scene, starts the world and the NPS processes, and reads the
run's summary and MCAP log.

Run by scripts/test.sh with TWINSWARM_BIN pointing at the debug binary.
"""

import importlib.util
import os

from conftest import ROOT
from pprz_ground import paparazzi_or_skip

SPEC = importlib.util.spec_from_file_location("nps_swarm", ROOT / "scripts" / "nps_swarm.py")
nps_swarm = importlib.util.module_from_spec(SPEC)
SPEC.loader.exec_module(nps_swarm)


def fly(tmp_path, *args):
    paparazzi_or_skip()
    bin_ = os.environ.get("TWINSWARM_BIN", str(ROOT / "target" / "debug" / "twinswarm"))
    return nps_swarm.main(["--twinswarm", bin_, "--out", str(tmp_path), *map(str, args)])


def test_an_nps_finken_takes_off_and_holds_its_flight_plans_metre(tmp_path):
    r = fly(tmp_path, "--count", 1, "--plan", "hover", "--duration", 40, "--first-ac", 40)
    assert r["crashes"] == [] and r["autopilots_left"] == [], r
    assert r["steps"] == 40_000, "one world step per autopilot step, every one answered"
    h = r["height_last_s"]["nps40"]
    # Over the last 10 s: within 5 cm of 1 m on average, 5 cm standard deviation (the real
    # FINken's IR height had 4-9 cm around its set point).
    assert abs(h["mean_m"] - 1.0) < 0.05 and h["sd_m"] < 0.05, h
    assert r["min_wall_clearance_m"] > 0.3, r


def test_an_nps_finken_flies_wall_avoid_for_a_minute_without_touching_a_wall(tmp_path):
    r = fly(tmp_path, "--count", 1, "--plan", "wall_avoid", "--duration", 60, "--first-ac", 41)
    assert r["crashes"] == [] and r["autopilots_left"] == [], r
    # The copter's rotor square never reached a wall of the 4 m x 3 m arena.
    assert r["min_wall_clearance_m"] > 0.0, r
    h = r["height_last_s"]["nps41"]
    assert abs(h["mean_m"] - 1.0) < 0.08, h


def test_two_runs_of_two_nps_finken_give_the_same_bits(tmp_path):
    a = fly(tmp_path / "a", "--count", 2, "--plan", "wall_avoid", "--duration", 20, "--first-ac", 41, "--no-log")
    b = fly(tmp_path / "b", "--count", 2, "--plan", "wall_avoid", "--duration", 20, "--first-ac", 41, "--no-log")
    for r in (a, b):
        assert r["autopilots_left"] == [] and r["steps"] == 20_000, r
    assert a["digests"] == b["digests"], (a, b)
