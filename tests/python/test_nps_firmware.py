"""The FINken's own firmware in the loop: the lab's modules of 16 Dec 2015 and the paper's
mixed-reality version of July 2015 (../shared/paparazzi/finken_firmware), compiled unchanged into
NPS aircraft and flown by `twinswarm run` in lockstep (docs/paparazzi.md, "The FINken's own
firmware"). Through scripts/nps_swarm.py, as tests/python/test_nps.py (the port's aircraft); a file
of its own so that pytest's two workers fly the two sets side by side (paparazzi/build_nps.sh
builds one aircraft at a time in the shared Paparazzi tree).

Run by scripts/test.sh with TWINSWARM_BIN pointing at the debug binary.
"""

from nps_flights import VIRTUAL_WALL, assert_uplink_in_the_lockstep, fly, nps_swarm, paparazzi_or_skip, uplink_runs


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
