"""Paparazzi's own rotorcraft autopilot in the loop: NPS FINken aircraft (paparazzi/, built
against the Paparazzi tree of ../shared/paparazzi) flown by `twinswarm run` as copters of kind
`autopilot`, in lockstep over a Unix-domain socket (nps_swarm.py's default; TCP where a test
says so) (docs/paparazzi.md). Through scripts/nps_swarm.py, which builds the aircraft, writes the
scene, starts the world and the NPS processes, and reads the run's summary and MCAP log.

Run by scripts/test.sh with TWINSWARM_BIN pointing at the debug binary.
"""

import re

from nps_flights import (SONAR_FIELDS, VIRTUAL_WALL, assert_uplink_in_the_lockstep, fly, nps_swarm, paparazzi_or_skip,
                         twinswarm_bin, uplink_runs)


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
    bin_ = twinswarm_bin()
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
