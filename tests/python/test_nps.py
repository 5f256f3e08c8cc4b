"""Paparazzi's own rotorcraft autopilot in the loop: NPS FINken aircraft (paparazzi/, built
against the Paparazzi tree of ../shared/paparazzi) flown by `twinswarm run` as copters of kind
`autopilot`, in lockstep over a Unix-domain socket (nps_swarm.py's default; TCP where a test
says so) (docs/paparazzi.md). Through scripts/nps_swarm.py, which builds the aircraft, writes the
scene, starts the world and the NPS processes, and reads the run's summary and MCAP log.

Run by scripts/test.sh with TWINSWARM_BIN pointing at the debug binary.
"""

import importlib.util
import os
import re

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


def test_two_runs_of_two_nps_finken_give_the_same_bits_over_a_socket_and_over_tcp(tmp_path):
    # The transport carries the same records: a run over a Unix-domain socket (the default) and
    # one over loopback TCP give the same bits.
    a = fly(tmp_path / "a", "--count", 2, "--plan", "wall_avoid", "--duration", 20, "--first-ac", 41, "--no-log")
    b = fly(tmp_path / "b", "--count", 2, "--plan", "wall_avoid", "--duration", 20, "--first-ac", 41, "--no-log",
            "--transport", "tcp")
    for r in (a, b):
        assert r["autopilots_left"] == [] and r["steps"] == 20_000, r
    assert (a["transport"], b["transport"]) == ("unix", "tcp")
    assert a["digests"] == b["digests"], (a, b)


def test_two_nps_finken_push_each_other_apart_through_their_sonars(tmp_path):
    # Started 0.9 m apart face to face, Wall-Avoid without the cruise: each front sonar sees
    # the other copter, nearer than the 1.2 m goal, and the firmware's lead-lag backs it off.
    # Nothing else moves them (a lone copter holds its place). With the module's sighting hold
    # (2 s; not in the firmware): the firmware's own four 30° cones lose a copter that drifts
    # sideways, and seed 7 then collides at 9.6 s (docs/paparazzi.md). The 6 m x 4 m arena leaves
    # room for the 1.2 m goal to the walls and between them.
    r = fly(tmp_path, "--count", 2, "--plan", "wall_avoid", "--duration", 25, "--first-ac", 47, "--arena", "6x4",
            "--gap", 0.9, "--cruise", "0,0", "--sighting-hold", 2)
    assert r["crashes"] == [] and r["autopilots_left"] == [], r
    assert r["min_pair_clearance_m"] > 0.0, "their rotor squares never met"
    assert r["max_pair_distance_m"] > 1.5, r


SONAR_FIELDS = ["real_front", "real_right", "real_back", "real_left", "virt_front", "virt_right", "virt_back",
                "virt_left", "fused_front", "fused_right", "fused_back", "fused_left", "ir", "virt_age", "wa_roll",
                "wa_pitch", "ll_roll", "ll_pitch", "uplinks"]
# A virtual-only wall across the arena, its face 1 m ahead of where the copter starts (the
# arena's centre, heading +x), 0.4 m thick.
VIRTUAL_WALL = "pos_m = [1.2, 0.0]; size_m = [0.4, 3.0, 2.5]; virtual_only = true"


def test_a_virtual_wall_reaches_an_nps_finken_through_the_real_link_and_turns_it_away(tmp_path, paparazzi_ground):
    """The world sends SONAR_UPLINK over Ivy to Paparazzi's own `link`, which forwards it over
    UDP to the NPS aircraft; its twinswarm_finken module fuses min(real, virtual) and its
    Wall-Avoid turns away from a wall only the simulation has. Its telemetry (TWINSWARM_SONAR)
    comes back through the same `link`."""
    pprz = paparazzi_or_skip()
    merged = pprz.home / "conf" / "userconf" / "twinswarm" / "messages.xml"
    # link's ports become the aircraft's (compiled in): the test's stand-in uplink socket goes.
    g = paparazzi_ground(messages_xml=merged if merged.exists() else None, server=False)
    g.uplink.close()
    rid = g.agent.bind(r"^46 TWINSWARM_SONAR (.*)")
    bin_ = os.environ.get("TWINSWARM_BIN", str(ROOT / "target" / "debug" / "twinswarm"))
    r = nps_swarm.main(list(map(str, [
        "--twinswarm", bin_, "--out", tmp_path / "fly", "--count", 1, "--plan", "wall_avoid", "--duration", 30,
        "--first-ac", 46, "--box", VIRTUAL_WALL, "--udp-out", g.link_port, "--udp-in", g.uplink_port,
        f"--run-arg=--ivy={g.bus}", f"--run-arg=--messages={merged}"])))
    assert r["autopilots_left"] == [], r
    assert r["crashes"] == [], f"it flew into the wall it was told of: {r['crashes']}"
    msgs = [dict(zip(SONAR_FIELDS, map(float, m[0].split()))) for m in g.agent.received(rid)]
    assert len(msgs) > 50, f"{len(msgs)} TWINSWARM_SONAR through link:\n{g.log('link')[-2000:]}"
    told = [m for m in msgs if m["virt_front"] > 0]
    assert told, "no virtual front reading ever reached the module"
    # The fused reading is the nearer of the two, and the virtual wall was the nearer one.
    assert all(abs(m["fused_front"] - min(v for v in (m["real_front"], m["virt_front"]) if v > 0)) < 0.011
               for m in told), told[:5]
    assert any(m["virt_front"] < m["real_front"] - 0.3 for m in told), told[:5]
    # It stayed clear of the virtual wall's near face (x = 1 m) with its rotor disc square.
    assert r["max_x_m"] < 1.0 - nps_swarm.HALF_WIDTH_M, r
    # The same flight without the uplink (no Ivy, so nothing tells the autopilot of the wall):
    # its centre flies into it (it exists only in the simulation), until the real wall behind
    # turns it.
    blind = nps_swarm.main(list(map(str, [
        "--twinswarm", bin_, "--out", tmp_path / "blind", "--count", 1, "--plan", "wall_avoid", "--duration", 30,
        "--first-ac", 41, "--box", VIRTUAL_WALL])))
    assert not [c for c in blind["crashes"] if c["cause"]["kind"] == "box"], blind
    assert blind["max_x_m"] > 1.0, blind


def uplink_runs(tmp_path, g, merged, first_ac, *args, runs=("a", "b")):
    """Flies the same run with the uplink through `link` (g) once per name in `runs`."""
    bin_ = os.environ.get("TWINSWARM_BIN", str(ROOT / "target" / "debug" / "twinswarm"))
    return [nps_swarm.main(list(map(str, [
        "--twinswarm", bin_, "--out", tmp_path / k, "--first-ac", first_ac, "--udp-out", g.link_port,
        "--udp-in", g.uplink_port, f"--run-arg=--ivy={g.bus}", f"--run-arg=--messages={merged}", *args])))
        for k in runs]


def assert_uplink_in_the_lockstep(r, ac):
    """The world counted the aircraft's uplink, and its NPS gave its autopilot what was named."""
    up = r["uplinks"][ac]
    assert up["uplink"] == "counted", r
    said = r["nps_said"][ac]
    assert "uplink in the lockstep" in said, said
    named, given = (int(v) for v in re.search(r"(\d+) named, (\d+) given", said).groups())
    # The uplink after the last step is named in no state; the last state may name one the
    # autopilot had no datalink event left to take.
    assert up["counted"] - 1 <= named <= up["counted"] and named - 1 <= given <= named, (said, up)
    return named


def test_the_uplink_through_link_takes_effect_at_the_step_the_world_names(tmp_path, paparazzi_ground):
    """The virtual-only wall's run above (SONAR_UPLINK over Ivy to Paparazzi's real `link`, over
    UDP to the aircraft), twice: the world counts the uplink messages it sends the aircraft and
    names the count in every state record (protocol v2); NPS gives its datalink parsing exactly
    those, waiting for any still on the way. So the two runs give the same bits, and the copter
    still turns away from the wall it was told of (docs/paparazzi.md, "Reproducible runs").
    `link` pings the aircraft every 0.1 s of wall time here (its default is 5 s): a datalink
    message the world does not count passes as it comes and moves none of the counted ones."""
    pprz = paparazzi_or_skip()
    merged = pprz.home / "conf" / "userconf" / "twinswarm" / "messages.xml"
    g = paparazzi_ground(messages_xml=merged if merged.exists() else None, server=False,
                         link_args=("-ping_period", "100"))
    g.uplink.close()
    a, b = uplink_runs(tmp_path, g, merged, 45, "--count", 1, "--plan", "wall_avoid", "--duration", 30,
                       "--box", VIRTUAL_WALL)
    for r in (a, b):
        assert r["autopilots_left"] == [] and r["crashes"] == [] and r["nps_exit"] == {}, r
        assert r["max_x_m"] < 1.0 - nps_swarm.HALF_WIDTH_M, r
        # From 0.5 s on, one per sonar update (20 Hz): 590 in 30 s.
        assert assert_uplink_in_the_lockstep(r, 45) > 550, r
    pings = [int(re.search(r"(\d+) other datalink messages", r["nps_said"][45]).group(1)) for r in (a, b)]
    assert sum(pings) > 0, pings
    assert a["digests"] == b["digests"], (a, b)


def test_the_papers_2015_07_firmware_takes_the_uplink_at_the_named_steps_too(tmp_path, paparazzi_ground):
    """The same for the paper's firmware, which parses SONAR_UPLINK with its own datalink function
    (finken_model_sensors.c, through v6.4's datalink parsing): the uplink in the lockstep is the
    flight model's (fdm_twinswarm), below every firmware's datalink. Its take-off is open loop
    into the ceiling (above), before its sonar centring runs: the test shows the uplink reaching
    it at the same steps, not the uplink steering it."""
    pprz = paparazzi_or_skip()
    merged = pprz.home / "conf" / "userconf" / "twinswarm" / "messages.xml"
    g = paparazzi_ground(messages_xml=merged if merged.exists() else None, server=False)
    g.uplink.close()
    a, b = uplink_runs(tmp_path, g, merged, 67, "--firmware", "2015-07", "--count", 1, "--plan", "hover",
                       "--duration", 10, "--box", VIRTUAL_WALL, "--no-log")
    for r in (a, b):
        assert r["autopilots_left"] == [] and r["nps_exit"] == {}, r
        assert assert_uplink_in_the_lockstep(r, 67) > 180, r
    assert a["digests"] == b["digests"], (a, b)


def test_a_stranger_is_refused_and_a_stopped_aircraft_ends_cleanly(tmp_path):
    # Aircraft 42 flies no copter of this scene: the world refuses it, NPS exits 2 saying why.
    # Aircraft 41 is stopped (SIGSTOP) for 12 s, past the world's 10 s step timeout: the world
    # drops it and goes on; continued, it reads why and exits 2 instead of waiting forever.
    r = fly(tmp_path, "--count", 1, "--plan", "wall_avoid", "--duration", 300, "--first-ac", 41, "--no-log",
            "--stranger", 42, "--stop", "41:0.5")
    assert r["nps_exit"].get(42) == 2, r
    assert "refused aircraft 42" in r["nps_said"][42] and "flies no copter of this scene" in r["nps_said"][42], r
    assert [x["ac_id"] for x in r["autopilots_refused"]] == [42], r
    assert r["autopilots_left"] == [41], r
    assert r["nps_exit"].get(41) == 2, r
    assert "dropped at step" in r["nps_said"][41] and "step timeout" in r["nps_said"][41], r


def test_the_finkens_own_2015_12_firmware_takes_off_and_holds_its_height_on_its_ir(tmp_path):
    """The lab's own firmware of 16 Dec 2015 (shared/paparazzi/finken_firmware/flight_2015-12:
    finken_model with its PID height controller, sonar_array_i2c, finken_ir_adc,
    finken_rc_passthrough; fink3.xml, aircraft 5) compiled unchanged into an NPS aircraft, its
    own flight plan free_flight.xml, no AHRS/INS bypass: the world's IR and sonar readings reach
    it only through its ADC buffer and I2C bus (docs/paparazzi.md, "The FINken's own firmware").
    The plan waits 10 s on the ground, then holds 0.6 m on the IR. The firmware has no
    horizontal control of its own (the pilot steered by RC, which NPS does not have), and this
    copter is untrimmed: the world's rotors have their seeded 2 % tolerances, whose torque the
    attitude loop (no integral) leaves as a steady tilt of about 2 deg; it drifts at about 1 m/s,
    hence the 40 m x 40 m arena; it reaches a wall at about 33 s (measured 2026-11-28)."""
    r = fly(tmp_path, "--firmware", "2015-12", "--count", 1, "--plan", "hover", "--duration", 32, "--first-ac", 62,
            "--arena", "40x40")
    assert r["autopilots_left"] == [] and r["steps"] == 32_000, r
    assert r["crashes"] == [], r
    gen = nps_swarm.PPRZ / "paparazzi" / "var" / "aircrafts" / "tw_fw201512_62" / "nps" / "generated" / "airframe.h"
    assert "NPS_BYPASS" not in gen.read_text(), "the AHRS and INS run on NPS's sensor models"
    rows = nps_swarm.states(tmp_path / "run.mcap")
    takeoff = next(float(s["t_s"]) for s in rows if float(s["pos_m"][2]) > 0.1)
    assert 10.0 < takeoff < 13.0, takeoff
    h = [float(s["pos_m"][2]) for s in rows if takeoff + 10 <= float(s["t_s"]) < takeoff + 20]
    mean = sum(h) / len(h)
    # Measured: mean 0.568 m, sd 0.075, 0.44-0.68 m (the IR read while tilted and drifting).
    assert abs(mean - 0.6) < 0.1, (mean, min(h), max(h))
    assert min(h) > 0.3 and max(h) < 0.9, (min(h), max(h))


def test_the_2015_12_firmware_trimmed_by_flying_holds_its_place_for_a_while(tmp_path):
    """The lab trimmed each copter (its IMU calibration, calib/$AC_ID_imu_calib.xml, not among the
    copies): nps_swarm.py --trim-flights flies two 30 s trim hovers and moves the copter's
    body-to-IMU roll and pitch by the mean attitude it held (FINKEN_FW_IMU_TRIM, set in the
    autopilot only; NPS's simulated IMU keeps its mounting). Trimmed, the drift of the untrimmed
    copter (about 1 m/s, above) is gone for the first seconds; what is left is the AHRS's own
    wandering tilt (NPS's gyro bias walk), a few tenths of a degree (measured 2026-11-28)."""
    r = fly(tmp_path, "--firmware", "2015-12", "--count", 1, "--plan", "hover", "--duration", 32, "--first-ac", 62,
            "--arena", "40x40", "--trim-flights", 2)
    assert r["autopilots_left"] == [] and r["crashes"] == [], r
    phi, theta = (float(v) for v in r["imu_trim"].split(","))
    # Measured: -1.91, 1.18 deg (seed 2016: the rotors' torque rolls this copter right)
    assert -3.0 < phi < -1.0 and abs(theta) < 2.5, r["imu_trim"]
    rows = nps_swarm.states(tmp_path / "run.mcap")
    takeoff = next(float(s["t_s"]) for s in rows if float(s["pos_m"][2]) > 0.1)
    assert 10.0 < takeoff < 13.0, takeoff
    at = lambda t: min(rows, key=lambda s: abs(float(s["t_s"]) - t))["pos_m"]
    a, b = at(takeoff + 5), at(takeoff + 15)
    moved = ((float(b[0]) - float(a[0])) ** 2 + (float(b[1]) - float(a[1])) ** 2) ** 0.5
    # Measured 1.55 m in these 10 s (untrimmed: 9.3 m)
    assert moved < 3.0, moved
    h = [float(s["pos_m"][2]) for s in rows if takeoff + 10 <= float(s["t_s"]) < takeoff + 20]
    assert abs(sum(h) / len(h) - 0.6) < 0.1 and min(h) > 0.3 and max(h) < 0.9, (min(h), max(h))


def test_the_papers_2015_07_firmware_compiles_unchanged_and_takes_off_open_loop(tmp_path):
    """The paper's mixed-reality firmware (shared/paparazzi/finken_firmware/mixed_reality_2015-07:
    finken_model with the SONAR_UPLINK min() fusion and sonar centring, sonar_array_i2c on i2c2,
    finken_ir_adc; quadrotor_lia_ovgu.xml; its flight plan ovgu_sonar.xml) compiled unchanged.
    The glue arms once the AHRS has aligned and restarts the plan's Takeoff block (the operator's
    strip button). Takeoff is open loop: 3 s at throttle 0.35, then 4 s at 0.45 (each stage's
    stage_time starts at 0). 0.45 was below hover on the lab's 2S copter; on Twinswarm's 3S
    FINken III with a full pack it is above hover: the copter lifts off in that stage and climbs at
    about 1 m/s into the 2.5 m ceiling before the height control begins (measured 2026-11-28)."""
    r = fly(tmp_path, "--firmware", "2015-07", "--count", 1, "--plan", "hover", "--duration", 12, "--first-ac", 66)
    assert r["autopilots_left"] == [] and r["steps"] == 12_000, r
    gen = nps_swarm.PPRZ / "paparazzi" / "var" / "aircrafts" / "tw_fw201507_66" / "nps" / "generated" / "airframe.h"
    assert "NPS_BYPASS" not in gen.read_text(), "the AHRS and INS run on NPS's sensor models"
    rows = nps_swarm.states(tmp_path / "run.mcap")
    takeoff = next(float(s["t_s"]) for s in rows if float(s["pos_m"][2]) > 0.1)
    # Measured: lift-off 5.53 s, ceiling 7.94 s
    assert 4.5 < takeoff < 7.0, takeoff
    assert [c["cause"]["kind"] for c in r["crashes"]] == ["ceiling"], r["crashes"]
    assert 6.5 < r["crashes"][0]["time_s"] < 10.0, r["crashes"]
