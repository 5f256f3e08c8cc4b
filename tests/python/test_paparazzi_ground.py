"""Twinswarm beside the real Paparazzi ground segment: `server` and `link` as built from
../shared/paparazzi (tudelft/paparazzi mavlabCourse2024, pprzlink 828de44; see
pprz_ground.py for how they are started and what they read).

Every test has its own loopback Ivy bus (127.255.255.255 and a free UDP port), its own
PAPARAZZI_HOME (a temporary directory) and free UDP ports for `link`, so tests can run side by
side. Without ../shared/paparazzi the tests skip loudly (failures under CI=true).

What is real and what is a stand-in:
- real: Paparazzi's `server` and `link` (OCaml, unmodified), `twinswarm run --ivy` (the virtual
  copters 201/202 of the embedded lab scene), pprzlink's own Python library (protocol 2.0, from
  the Paparazzi tree) to make and decode the frames on `link`'s UDP side;
- ivy-python stand-ins: the agent `PyGround` that receives what `server` publishes; in the
  uplink tests it also sends the datalink texts in place of Twinswarm (`ground_dl SONAR_UPLINK
  …`, until Twinswarm emits SONAR_UPLINK itself) and in test_c the telemetry of aircraft 201;
- a Python UDP socket stands in for the aircraft's modem: it sends ALIVE frames so that `link`
  knows the aircraft, and receives what `link` sends it.
"""
import json
import math
import re
import shutil
import struct
import subprocess
import time

import pytest

import pprz_ground
from conftest import shared_data_or_skip
from pprz_ground import Aircraft

# WGS84, as Paparazzi's Latlong module has it
WGS84_A = 6378137.0
WGS84_E2 = 6.69437999014e-3


def ecef_to_geodetic(x: float, y: float, z: float) -> tuple[float, float, float]:
    """(lat rad, lon rad, height m) of an ECEF point (iterated to well below a millimetre)."""
    lon = math.atan2(y, x)
    p = math.hypot(x, y)
    lat = math.atan2(z, p * (1 - WGS84_E2))
    for _ in range(10):
        n = WGS84_A / math.sqrt(1 - WGS84_E2 * math.sin(lat) ** 2)
        h = p / math.cos(lat) - n
        lat = math.atan2(z, p * (1 - WGS84_E2 * n / (n + h)))
    n = WGS84_A / math.sqrt(1 - WGS84_E2 * math.sin(lat) ** 2)
    return lat, lon, p / math.cos(lat) - n


def ned_to_ecef(ref: tuple, north: float, east: float, down: float) -> tuple:
    """The ECEF point `north`, `east`, `down` metres from the ECEF point `ref` (as
    Latlong.ecef_of_ned does: the local frame of ref's geodetic latitude and longitude)."""
    lat, lon, _ = ecef_to_geodetic(*ref)
    sl, cl, so, co = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)
    dx = -sl * co * north - so * east - cl * co * down
    dy = -sl * so * north + co * east - cl * so * down
    dz = cl * north - sl * down
    return ref[0] + dx, ref[1] + dy, ref[2] + dz


def run_twinswarm(twinswarm_bin, bus: str, duration_s: float, *extra: str) -> subprocess.Popen:
    """`twinswarm run` of the embedded lab scene (virtual copters 201 and 202) on the Ivy bus
    alone, in real time."""
    cmd = [str(twinswarm_bin), "run", "--no-bus", "--ivy", bus, "--no-log", "--realtime",
           "--duration", str(duration_s), "--json", *extra]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def finish(proc: subprocess.Popen, timeout_s: float = 30) -> dict:
    try:
        out, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        pytest.fail(f"twinswarm did not finish within {timeout_s} s: {err[-3000:]}")
    assert proc.returncode == 0, f"twinswarm failed ({proc.returncode}): {err[-3000:]}"
    return json.loads(out)


def flight_params(agent, rid) -> list:
    """(arrival, ac_id, {field: value}) of every ground FLIGHT_PARAM received."""
    names = ["roll", "pitch", "heading", "lat", "long", "speed", "course", "alt", "climb", "agl",
             "unix_time", "itow", "airspeed"]
    out = []
    for t, groups in agent.received_timed(rid):
        ac_id, rest = groups
        out.append((t, ac_id, dict(zip(names, (float(v) for v in rest.split(" "))))))
    return out


def wait_for(cond, timeout_s: float, step_s: float = 0.05):
    """cond()'s first true value within timeout_s, else its last value."""
    deadline = time.monotonic() + timeout_s
    while True:
        v = cond()
        if v or time.monotonic() >= deadline:
            return v
        time.sleep(step_s)


class TimedAgent:
    """Adds arrival times to test_ivy.Agent's records."""

    def __init__(self, agent):
        self.agent = agent
        self.times: dict[int, list[float]] = {}

    def bind(self, regex: str) -> int:
        box: list[int] = []
        a = self.agent

        def on_msg(_client, *groups):
            with a.lock:
                a.got.setdefault(box[0], []).append(groups)
                self.times.setdefault(box[0], []).append(time.monotonic())

        rid = a.server.bind_msg(on_msg, regex)
        box.append(rid)
        return rid

    def received_timed(self, rid: int) -> list:
        with self.agent.lock:
            return list(zip(self.times.get(rid, []), self.agent.got.get(rid, [])))


def test_a_server_registers_a_virtual_copter_and_places_it_where_twinswarm_says(paparazzi_ground, twinswarm_bin):
    """The stock pprzlink v1.0 messages.xml; `server` beside `twinswarm run --ivy`."""
    g = paparazzi_ground(link=False)
    watch = TimedAgent(g.agent)
    fp_rid = watch.bind(r"^ground FLIGHT_PARAM (\S+) (.*)")
    new_rid = watch.bind(r"^ground NEW_AIRCRAFT (\S+)")
    tw_fp = watch.bind(r"^(20[12]) ROTORCRAFT_FP (.*)")
    tw_ref = watch.bind(r"^(20[12]) INS_REF (.*)")
    g.sync()  # server has our regexes before Twinswarm's first ALIVE
    # ALIVE goes out every 2.1 s and INS_REF every 5.1 s; server binds an aircraft's texts only
    # once its ALIVE registered it, so the INS_REF it first gets may be the one at 5.1 s.
    summary = finish(run_twinswarm(twinswarm_bin, g.bus, 9.0))
    log = g.log("server")
    assert g.alive()["server"], log[-3000:]

    new = {groups[0] for _t, groups in watch.received_timed(new_rid)}
    assert {"201", "202"} <= new, (new, log[-3000:])
    assert "MD5 is ZERO" in log
    assert "not found" not in log, log[-3000:]
    # What pprzlink v1.0 lacks (README "What was seen"): the reason for the lab's messages.xml.
    assert "Unknown message FINKEN_SENSOR_MODEL in class telemetry from 201" in log

    params = flight_params(watch, fp_rid)
    placed = [(t, ac, f) for t, ac, f in params if ac == "201" and f["lat"] != 0.0]
    assert len(placed) >= 3, (len(params), params[-3:], log[-3000:])

    # Where Twinswarm says 201 is: its own INS_REF and ROTORCRAFT_FP texts, as the agent got them.
    ref_fields = [int(v) for v in watch.received_timed(tw_ref)[0][1][1].split(" ")[:7]]
    ref = tuple(v / 100.0 for v in ref_fields[:3])
    lat0, lon0, h0 = ecef_to_geodetic(*ref)
    assert abs(math.degrees(lat0) - pprz_ground.ARENA_LAT0) < 1e-6
    assert abs(math.degrees(lon0) - pprz_ground.ARENA_LON0) < 1e-6
    hmsl0 = ref_fields[6] / 1000.0
    fps = [(t, [int(v) for v in groups[1].split(" ")]) for t, groups in watch.received_timed(tw_fp) if groups[0] == "201"]
    assert len(fps) > 20, len(fps)
    for t, _ac, f in placed:
        # the texts the server had most likely decoded last: those of the last second
        best = None
        for tf, v in fps:
            if t - 1.0 <= tf <= t + 0.1:
                east, north, up = v[0] / 256.0, v[1] / 256.0, v[2] / 256.0  # ROTORCRAFT_FP: int32, 1/256 m
                assert abs(east) < 3.0 and abs(north) < 3.0 and -0.1 < up < 3.0, v  # in the 4 m x 3 m arena
                lat, lon, _h = ecef_to_geodetic(*ned_to_ecef(ref, north, east, -up))
                d = math.hypot((math.radians(f["lat"]) - lat) * WGS84_A,
                               (math.radians(f["long"]) - lon) * WGS84_A * math.cos(lat))
                if best is None or d < best[0]:
                    best = (d, up)
        assert best is not None, f"no ROTORCRAFT_FP of 201 in the second before FLIGHT_PARAM at {t}"
        assert best[0] < 0.03, (best, f)  # FLIGHT_PARAM lat/long are printed to 1e-7 deg, 1 cm
        assert abs(f["agl"] - best[1]) < 0.03, (best, f)  # ground_alt = INS_REF hmsl0
        assert abs(f["alt"] - (hmsl0 + best[1])) < 0.05, (best, f, hmsl0)
    assert summary["bus"]["ivy"]["peers_joined"] >= 2, summary["bus"]["ivy"]


def test_b_with_the_labs_messages_xml_server_decodes_the_finken_telemetry(paparazzi_ground, lab_messages_xml, twinswarm_bin):
    """pprzlink v1.0 with the FINken telemetry merged in (pprz_ground.lab_messages_xml), for
    `server` and for `twinswarm run --messages`: `server` decodes every message Twinswarm's
    virtual copters send, as its own log shows."""
    g = paparazzi_ground(lab_messages_xml, link=False, server_log=True)
    watch = TimedAgent(g.agent)
    fp_rid = watch.bind(r"^ground FLIGHT_PARAM (\S+) (.*)")
    g.sync()
    # Twinswarm encodes by the same file (`--messages`), as a lab would run it
    finish(run_twinswarm(twinswarm_bin, g.bus, 5.0, "--messages", str(lab_messages_xml)))
    time.sleep(0.3)
    log = g.log("server")
    assert "Unknown message" not in log, log[-3000:]
    assert "incorrect number of fields" not in log, log[-3000:]
    assert any(ac == "201" for _t, ac, _f in flight_params(watch, fp_rid)), log[-3000:]
    # server's own log (var/logs/*.data): `<time> <ac_id> <NAME> <values>` per decoded message
    decoded: dict[str, list[list[str]]] = {}
    for line in g.server_data_log().splitlines():
        parts = line.split(" ")
        if len(parts) >= 3 and parts[1] == "201":
            decoded.setdefault(parts[2], []).append(parts[3:])
    want = {"FINKEN_SENSOR_MODEL": 21, "SONAR_ARRAY": 4, "FINKEN_ACTUATORS_SET_POINT": 4,
            "FINKEN_IR_ADC": 2, "ROTORCRAFT_STATUS": 12, "ROTORCRAFT_FP": 15, "ATTITUDE": 3}
    for name, n_fields in want.items():
        assert decoded.get(name), (name, sorted(decoded))
        assert all(len(v) == n_fields for v in decoded[name]), (name, decoded[name][-1])
    assert len(decoded["FINKEN_SENSOR_MODEL"]) >= 10, len(decoded["FINKEN_SENSOR_MODEL"])


def test_c_the_finken_era_messages_xml_as_it_is_half_works(paparazzi_ground, tmp_path):
    """FINken_conf_messages.xml, unchanged (pre-pprzlink: classes without ids): today's `server`
    reads it, registers the aircraft and decodes FINKEN_SENSOR_MODEL, but its periodic
    per-aircraft messages stop at ENGINE_STATUS, whose FINken-era layout lacks the `charge` field
    today's server fills, every 0.5 s. Hence the merged lab messages.xml of test_b.
    (Stand-in: ivy-python sends the telemetry of aircraft 201.)"""
    finken = shared_data_or_skip("paparazzi_finken")
    mx = tmp_path / "finken" / "messages.xml"
    mx.parent.mkdir()
    shutil.copy(finken / "FINken_conf_messages.xml", mx)
    shutil.copy(finken / "FINken_conf_messages.dtd", mx.parent / "messages.dtd")
    g = paparazzi_ground(mx, link=False, server_log=True)
    watch = TimedAgent(g.agent)
    fp_rid = watch.bind(r"^ground FLIGHT_PARAM (\S+) (.*)")
    ap_rid = watch.bind(r"^ground AP_STATUS (\S+) (.*)")
    g.sync()
    assert g.send("201 ALIVE " + ",".join(["0"] * 16)) == 1
    deadline = time.monotonic() + 10
    sensor = "201 FINKEN_SENSOR_MODEL 80 90 100 110 0 0 0.5 0.25 0.75 0.0 0.0 0.1 0 0 0 0 0 0 0 0 0"
    while g.send(sensor) == 0:  # until server has bound aircraft 201's texts
        assert time.monotonic() < deadline, g.log("server")[-3000:]
        time.sleep(0.02)
    time.sleep(1.5)
    log = g.log("server")
    assert "Unknown message" not in log, log[-3000:]
    assert " 201 FINKEN_SENSOR_MODEL 80 90 100 110 0 0 0.5 0.25 0.75 " in g.server_data_log()
    assert any(ac == "201" for _t, ac, _f in flight_params(watch, fp_rid))
    assert "unknown field 'charge' in message 'ENGINE_STATUS'" in log, log[-3000:]
    assert watch.received_timed(ap_rid) == []  # sent after ENGINE_STATUS: never


def pprz_v2_frame(sender: int, receiver: int, class_id: int, msg_id: int, payload: bytes) -> bytes:
    """A pprzlink 2.0 frame written out here, independently of pprzlink's library: STX 0x99,
    length (the whole frame), sender, receiver, component << 4 | class, message id, payload,
    two Fletcher checksum bytes over everything after STX."""
    body = struct.pack("<BBBBB", 6 + len(payload) + 2, sender, receiver, class_id, msg_id) + payload
    ck_a = ck_b = 0
    for b in body:
        ck_a = (ck_a + b) % 256
        ck_b = (ck_b + ck_a) % 256
    return b"\x99" + body + bytes([ck_a, ck_b])


def test_d_link_forwards_a_datalink_text_to_its_aircraft_as_a_pprzlink_frame(paparazzi_ground, lab_messages_xml):
    """The uplink path through the real `link`: SONAR_UPLINK (datalink 153, link="forwarded")
    in the lab's messages.xml. Stand-ins: ivy-python sends the texts Twinswarm is to send; a UDP
    socket plays the FINken's modem (ALIVE frames from it make aircraft 5 live for `link`)."""
    g = paparazzi_ground(lab_messages_xml, aircraft=[Aircraft("FINken_01", 5)])
    watch = TimedAgent(g.agent)
    alive_rid = watch.bind(r"^(5) ALIVE (.*)")
    g.sync()
    g.keep_alive(5)
    # link relays the aircraft's ALIVE on Ivy
    assert wait_for(lambda: watch.received_timed(alive_rid), 10.0), g.log("link")[-3000:]
    assert watch.received_timed(alive_rid)[0][1] == ("5", ",".join(["0"] * 16))

    # link binds `^([^ ]*) +(SONAR_UPLINK( .*|$))` for a forwarded datalink message: any sender
    # (server's own datalink texts use `ground_dl`), then the fields in messages.xml order.
    assert g.send("ground_dl SONAR_UPLINK 5 0 100 200 300 400") == 1
    frames = g.recv_uplink(5.0, name="SONAR_UPLINK")
    assert len(frames) == 1, frames
    f = frames[0]
    assert (f.sender_id, f.receiver_id, f.component_id, f.class_id, f.msg_class) == (0, 5, 0, 2, "datalink")
    assert f.fields == {"ac_id": 5, "unused": 0, "front": 100, "left": 200, "back": 300, "right": 400}
    assert f.raw == pprz_v2_frame(0, 5, 2, 153, struct.pack("<BBHHHH", 5, 0, 100, 200, 300, 400)), f.raw.hex()

    # the same through server: a ground agent's RAW_DATALINK becomes `ground_dl SONAR_UPLINK …`
    sent_rid = watch.bind(r"^(ground_dl) SONAR_UPLINK (.*)")
    g.sync()
    assert g.send("gcs RAW_DATALINK 5 SONAR_UPLINK;5;0;11;22;33;65535") == 1
    frames = g.recv_uplink(5.0, name="SONAR_UPLINK")
    assert [x.fields for x in frames] == [{"ac_id": 5, "unused": 0, "front": 11, "left": 22, "back": 33, "right": 65535}]
    assert wait_for(lambda: watch.received_timed(sent_rid), 5.0)
    assert [g for _t, g in watch.received_timed(sent_rid)] == [("ground_dl", "5 0 11 22 33 65535")]

    # an aircraft link has not heard from gets nothing; a message not in messages.xml matches
    # no regex of link's at all (dropped without a word, as README says of VIRTUAL_SONAR)
    assert g.send("ground_dl SONAR_UPLINK 6 0 1 2 3 4") == 1
    assert g.send("ground_dl VIRTUAL_SONAR 5 120 65535 87 300") == 0
    later = [x for x in g.recv_uplink(1.5, count=100) if x.name != "PING"]
    assert later == [], later
    assert all(g.alive().values()), (g.log("link")[-2000:], g.log("server")[-2000:])
    assert "rror" not in g.log("link"), g.log("link")[-3000:]


def test_e_the_fixture_gives_private_buses_and_ports(paparazzi_ground):
    """Two ground segments side by side: their buses, homes and ports differ, each sees only
    its own agents."""
    a = paparazzi_ground(server=False, agent_name="PyA")
    b = paparazzi_ground(server=False, agent_name="PyB")
    assert a.bus != b.bus and a.home != b.home
    assert len({a.link_port, a.uplink_port, b.link_port, b.uplink_port}) == 4
    assert re.fullmatch(r"127\.255\.255\.255:\d+", a.bus)
    assert a.agent.server.get_client_with_name("PyB") == [] and b.agent.server.get_client_with_name("PyA") == []
    assert len(a.agent.server.get_client_with_name("Link")) == 1
