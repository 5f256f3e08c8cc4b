"""Real FINken flights in the loop: Paparazzi's own log of the 16 Dec 2015 linked flight played
onto a private Ivy bus by `twinswarm replay`, received by ivy-python at the recorded rate and
followed by a `twinswarm run --ivy` twin of aircraft 5; and Twinswarm's SONAR_UPLINK crossing
Paparazzi's real `link` to a FINken aircraft.

Independent peers: ivy-python (the Ivy side), Paparazzi's own `link` built from
../shared/paparazzi and pprzlink's Python library (the aircraft side). The flight log is read
from ../shared/data (skipped loudly without it, a failure under CI=true).
"""

import json
import statistics
import subprocess
import threading
import time

from conftest import ROOT, shared_data_or_skip
from pprz_ground import Aircraft
from test_ivy import Agent, bus  # noqa: F401  (the `bus` fixture)

SCENE = ROOT / "assets" / "scenes" / "mixed_lab.toml"
PAIRING = ROOT / "assets" / "pairing" / "mixed_lab.xml"
FLIGHT = "15_12_16__13_55_00"


def flight_files():
    d = shared_data_or_skip("finken_flights", "report_2015-12-16")
    return d / f"{FLIGHT}.data", d / f"{FLIGHT}.log"


def recorded(data, names, t0, t1):
    """(time, text) of aircraft 5's `names` in the log between t0 and t1, as link put them."""
    out = []
    for line in data.read_text().splitlines():
        parts = line.split(" ", 1)
        if len(parts) == 2 and parts[1].startswith("5 ") and parts[1].split(" ")[1] in names:
            t = float(parts[0])
            if t0 <= t <= t1:
                out.append((t, parts[1]))
    return out


class Timed(Agent):
    """An ivy-python agent that also stamps what it receives."""

    def bind_timed(self, regex):
        box = []

        def on_msg(agent, *groups):
            with self.lock:
                self.got.setdefault(box[0], []).append((time.monotonic(), groups))

        box.append(self.server.bind_msg(on_msg, regex))
        return box[0]


def replay(twinswarm_bin, data, bus, t0, t1, *extra):
    cmd = [str(twinswarm_bin), "replay", str(data), "--ivy", bus, "--no-bus", "--from", str(t0), "--to", str(t1),
           "--wait-for-subscriber", "15", *extra]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_replay_plays_the_flight_onto_ivy_at_its_recorded_rate(twinswarm_bin, bus):
    data, _ = flight_files()
    names = {"FINKEN_SENSOR_MODEL", "AHRS_EULER_INT"}
    want = recorded(data, names, 840.0, 846.0)
    a = Timed("PyLinkWatcher", bus)
    rid = a.bind_timed(r"^(5) (FINKEN_SENSOR_MODEL|AHRS_EULER_INT) (.*)")
    a.start()
    try:
        proc = replay(twinswarm_bin, data, bus, 840.0, 846.0)
        out, err = proc.communicate(timeout=60)
    finally:
        a.stop()
    assert proc.returncode == 0, err
    got = a.received(rid)
    # Every text, byte for byte, in order.
    assert [f"{g[0]} {g[1]} {g[2]}" for _t, g in got] == [text for _t, text in want], out
    # At the recorded times: the same span and the same median gap of FINKEN_SENSOR_MODEL.
    span_rec = want[-1][0] - want[0][0]
    span_got = got[-1][0] - got[0][0]
    assert abs(span_got - span_rec) < 0.3, (span_got, span_rec)
    fsm_rec = [t for t, text in want if " FINKEN_SENSOR_MODEL " in text]
    fsm_got = [t for t, g in got if g[1] == "FINKEN_SENSOR_MODEL"]
    gap = lambda ts: statistics.median(b - a for a, b in zip(ts, ts[1:]))  # noqa: E731
    assert abs(gap(fsm_got) - gap(fsm_rec)) < 0.005, (gap(fsm_got), gap(fsm_rec))
    # The other messages of the window went too (LINK_REPORT does not read: its link_id is -1).
    assert "0 failed" in out and "1028 unreadable lines skipped" in out, out


def test_a_twin_of_aircraft_5_follows_the_replayed_flight(twinswarm_bin, bus):
    data, log = flight_files()
    watch = Timed("PyUplinkWatcher", bus)
    uplink_rid = watch.bind_timed(r"^(\S+) (SONAR_UPLINK|VIRTUAL_SONAR) (.*)")
    watch.start()
    try:
        # The run decodes with the definitions the flight was logged with.
        run = subprocess.Popen(
            [str(twinswarm_bin), "run", str(SCENE), "--pairing", str(PAIRING), "--no-bus", "--ivy", bus, "--no-log",
             "--realtime", "--duration", "12", "--json", "--messages", str(log)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert watch.joined.wait(15), "Twinswarm never joined the bus"
        rep = replay(twinswarm_bin, data, bus, 836.0, 844.0)
        rep_out, rep_err = rep.communicate(timeout=60)
        out, err = run.communicate(timeout=60)
    finally:
        watch.stop()
    assert rep.returncode == 0, rep_err
    assert run.returncode == 0, err
    summary = json.loads(out)
    twin = summary["twins"]["finken_01"]
    assert twin["inputs_applied"] > 400, twin
    sources = summary["bus"]["telemetry"]["sources"]["5"]
    assert "AHRS_EULER_INT" in sources["attitude"], sources
    assert "FINKEN_SENSOR_MODEL" in sources["height"], sources
    assert "FINKEN_SENSOR_MODEL" in sources["sonar"], sources
    # The 2015 ground segment's messages.xml defines no uplink: none is sent, and the start says so.
    assert "twin finken_01 (aircraft 5): no virtual-sonar uplink" in err, err
    assert watch.received(uplink_rid) == []


def test_sonar_uplink_crosses_the_real_link_to_a_finken(twinswarm_bin, paparazzi_ground, lab_messages_xml):
    """The lab's messages.xml (pprzlink v1.0 with the FINken messages and the mixed-reality
    fork's SONAR_UPLINK) makes Twinswarm send SONAR_UPLINK; Paparazzi's own `link` forwards it to
    aircraft 5 as a pprzlink frame, decoded here by pprzlink's Python library."""
    g = paparazzi_ground(lab_messages_xml, aircraft=[Aircraft("FINken_01", 5)])
    g.sync()
    g.keep_alive(5)
    err_box = []

    def run():
        p = subprocess.run(
            [str(twinswarm_bin), "run", str(SCENE), "--pairing", str(PAIRING), "--no-bus", "--ivy", g.bus,
             "--no-log", "--realtime", "--duration", "6", "--json", "--messages", str(lab_messages_xml)],
            capture_output=True, text=True, timeout=90)
        err_box.append(p)

    t = threading.Thread(target=run)
    t.start()
    frames = g.recv_uplink(20.0, count=20, name="SONAR_UPLINK")
    t.join(90)
    p = err_box[0]
    assert p.returncode == 0, p.stderr[-3000:]
    assert "twin finken_01 (aircraft 5): virtual sonar as SONAR_UPLINK from `dl`" in p.stderr, p.stderr
    assert len(frames) >= 10, (frames, g.log("link")[-2000:])
    for f in frames:
        assert f.receiver_id == 5 and f.msg_class == "datalink", f
        v = f.fields
        assert v["ac_id"] == 5 and v["unused"] == 255, v
        assert all(0 <= v[k] <= 765 for k in ("front", "left", "back", "right")), v
    # The mixed lab's virtual copter and virtual-only crate are in range of some sonar of the
    # twin at some time: not every reading is "nothing virtual" (765).
    assert any(f.fields[k] < 765 for f in frames for k in ("front", "left", "back", "right")), frames
