"""Twinswarm on a real Ivy bus, against ivy-python 4.0 (PyPI) as an independent peer.

Every test uses its own loopback bus (127.255.255.255 and a free UDP port), so tests can run
side by side. The simulator runs as `twinswarm run --no-bus --ivy BUS` (Ivy alone) in real
time; the Python agents join first, so the simulator's hello makes them connect to it.
"""
import json
import re
import socket
import subprocess
import threading
import time

import pytest
from ivy.ivy import IvyApplicationConnected, IvyApplicationDisconnected, IvyServer

from conftest import ROOT

SCENE = ROOT / "assets" / "scenes" / "mixed_lab.toml"
PAIRING = ROOT / "assets" / "pairing" / "mixed_lab.xml"
# The regex Paparazzi's `link` binds for a datalink message marked link="forwarded"
# (sw/ground_segment/tmtc/link.ml: `^([^ ]*) +(NAME( .*|$))`).
LINK_VIRTUAL_SONAR = r"^([^ ]*) +(VIRTUAL_SONAR( .*|$))"


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def bus() -> str:
    return f"127.255.255.255:{free_udp_port()}"


class Agent:
    """An ivy-python agent that records what it receives and who joins and leaves."""

    def __init__(self, name: str, bus: str):
        self.events: list[tuple[str, str]] = []
        self.joined = threading.Event()
        self.got: dict[int, list[tuple[str, ...]]] = {}
        self.lock = threading.Lock()

        def on_app(agent, event):
            with self.lock:
                self.events.append(("joined" if event == IvyApplicationConnected else "left", agent.agent_name))
            if event == IvyApplicationConnected and agent.agent_name == "Twinswarm":
                self.joined.set()

        self.server = IvyServer(name, app_callback=on_app, usesDaemons=True)
        self.bus = bus

    def bind(self, regex: str) -> int:
        box: list[int] = []

        def on_msg(agent, *groups):
            with self.lock:
                self.got.setdefault(box[0], []).append(groups)

        rid = self.server.bind_msg(on_msg, regex)
        box.append(rid)
        return rid

    def received(self, rid: int) -> list[tuple[str, ...]]:
        with self.lock:
            return list(self.got.get(rid, []))

    def start(self):
        self.server.start(self.bus)
        return self

    def stop(self):
        if self.server.isAlive():
            self.server.stop()

    def twinswarm(self):
        clients = self.server.get_client_with_name("Twinswarm")
        return clients[0] if clients else None


def run_sim(twinswarm_bin, bus: str, duration_s: float, *extra: str) -> subprocess.Popen:
    cmd = [
        str(twinswarm_bin), "run", str(SCENE), "--pairing", str(PAIRING), "--no-bus", "--ivy", bus,
        "--no-log", "--realtime", "--duration", str(duration_s), "--json", *extra,
    ]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def finish(proc: subprocess.Popen, timeout_s: float = 60) -> dict:
    out, err = proc.communicate(timeout=timeout_s)
    assert proc.returncode == 0, f"twinswarm failed ({proc.returncode}): {err[-3000:]}"
    return json.loads(out)


def test_a_virtual_copters_rotorcraft_fp_reaches_a_python_agent(twinswarm_bin, bus):
    a = Agent("PyWatcher", bus)
    rid = a.bind(r"^(\S*) ROTORCRAFT_FP (.*)")
    a.start()
    try:
        proc = run_sim(twinswarm_bin, bus, 4.0)
        assert a.joined.wait(15), "Twinswarm never connected to the Python agent"
        summary = finish(proc)
    finally:
        a.stop()
    got = a.received(rid)
    senders = {g[0] for g in got}
    # The scene's virtual copter (ac_id 101) publishes ROTORCRAFT_FP every 0.25 s.
    assert "101" in senders, senders
    for groups in got:
        assert len(groups) == 2
        fields = groups[1].split(" ")
        assert len(fields) >= 10 and all(re.fullmatch(r"-?\d+", f) for f in fields), groups
    assert len([g for g in got if g[0] == "101"]) >= 8, len(got)
    ivy = summary["bus"]["ivy"]
    assert ivy["peers_joined"] >= 1 and ivy["msgs_sent"] >= len(got)


def link_texts(_t_s: float):
    """What `link` relays for a hovering FINken, aircraft 5."""
    return {
        "FINKEN_ACTUATORS_SET_POINT": (0.022, "5 FINKEN_ACTUATORS_SET_POINT 0.000000 0.000000 0.000000 52.000000"),
        "ATTITUDE": (0.022, "5 ATTITUDE 0.000000 0.000000 0.000000"),
        "FINKEN_IR_ADC": (0.05, "5 FINKEN_IR_ADC 0.800000 512"),
        "SONAR_ARRAY": (0.05, "5 SONAR_ARRAY 140 160 140 120"),
    }


def test_b_a_python_link_drives_the_twin_and_receives_virtual_sonar(twinswarm_bin, bus):
    link = Agent("Link", bus)
    rid = link.bind(LINK_VIRTUAL_SONAR)
    link.start()
    try:
        proc = run_sim(twinswarm_bin, bus, 6.0)
        assert link.joined.wait(15), "Twinswarm never connected"
        time.sleep(0.3)  # its regexes arrive right after the handshake
        t0 = time.monotonic()
        due = {name: 0.0 for name in link_texts(0)}
        sent = 0
        while time.monotonic() - t0 < 4.0:
            now = time.monotonic() - t0
            for name, (period, text) in link_texts(now).items():
                if now >= due[name]:
                    due[name] += period
                    sent += link.server.send_msg(text)
            time.sleep(0.002)
        summary = finish(proc)
    finally:
        link.stop()
    assert sent > 300, sent
    twin = summary["twins"]["finken_01"]
    assert twin["inputs_applied"] > 200, twin
    got = link.received(rid)
    assert len(got) > 20, len(got)
    sender, text, _ = got[-1]
    assert sender == "ground_dl"
    fields = text.split(" ")
    assert fields[0] == "VIRTUAL_SONAR" and fields[1] == "5" and len(fields) == 6, text
    assert all(0 <= int(v) <= 65535 for v in fields[2:])
    arrivals = {a["message"]: a["count"] for a in summary["bus"]["telemetry"]["arrivals"] if a["ac_id"] == 5}
    assert arrivals.get("FINKEN_ACTUATORS_SET_POINT", 0) > 100, arrivals


def test_c_delregexp_bye_and_die_are_honoured(twinswarm_bin, bus):
    a = Agent("PyUnbinder", bus)
    rid = a.bind(r"^(101) ATTITUDE (.*)")
    b = Agent("PyKiller", bus)
    a.start()
    b.start()
    try:
        proc = run_sim(twinswarm_bin, bus, 60.0)
        assert a.joined.wait(15) and b.joined.wait(15)
        time.sleep(1.0)
        before = len(a.received(rid))
        assert before > 10, before
        # DelRegexp: nothing more arrives for that regex.
        a.server.unbind_msg(rid)
        time.sleep(0.5)
        settled = len(a.received(rid))
        time.sleep(1.0)
        assert len(a.received(rid)) == settled, "messages still arrive after DelRegexp"
        # Bye: PyUnbinder leaves.
        a.stop()
        time.sleep(0.5)
        # Die: PyKiller asks Twinswarm to quit; it ends its run cleanly long before 60 s.
        tw = b.twinswarm()
        assert tw is not None
        t_die = time.monotonic()
        tw.send_die_message(msg="test over")
        summary = finish(proc, timeout_s=20)
        assert time.monotonic() - t_die < 10
    finally:
        a.stop()
        b.stop()
    assert summary["interrupted"] is True
    ivy = summary["bus"]["ivy"]
    left = [e["app_name"] for e in ivy["events"] if e["what"] == "left"]
    assert "PyUnbinder" in left, ivy["events"]


def test_d_a_bad_regex_gets_an_error_and_the_run_goes_on(twinswarm_bin, bus):
    a = Agent("PyBadRegex", bus)
    # Python's re accepts look-behind; the regex crate does not: Twinswarm answers with Error.
    bad = a.bind(r"^(?<=x)(\S*) ATTITUDE (.*)")
    good = a.bind(r"^(101) ATTITUDE (.*)")
    a.start()
    try:
        proc = run_sim(twinswarm_bin, bus, 3.0)
        assert a.joined.wait(15)
        summary = finish(proc)
    finally:
        a.stop()
    assert len(a.received(good)) > 20
    assert a.received(bad) == []
    ivy = summary["bus"]["ivy"]
    assert ivy["dropped"].get("peer regex refused") == 1, ivy["dropped"]


def test_e_peers_join_and_leave_mid_run(twinswarm_bin, bus):
    first = Agent("PyFirst", bus)
    rid1 = first.bind(r"^(101) ATTITUDE (.*)")
    first.start()
    late = None
    try:
        proc = run_sim(twinswarm_bin, bus, 6.0)
        assert first.joined.wait(15)
        time.sleep(1.0)
        # A peer that joins after Twinswarm: its hello makes Twinswarm connect to it.
        late = Agent("PyLate", bus)
        rid2 = late.bind(r"^(101) ATTITUDE (.*)")
        late.start()
        assert late.joined.wait(10), "Twinswarm did not connect to a peer that joined mid-run"
        time.sleep(1.0)
        first.stop()
        n_first = len(first.received(rid1))
        time.sleep(1.0)
        summary = finish(proc)
    finally:
        first.stop()
        if late:
            late.stop()
    assert n_first > 20
    assert len(late.received(rid2)) > 20
    ivy = summary["bus"]["ivy"]
    names = [(e["what"], e["app_name"]) for e in ivy["events"]]
    assert ("joined", "PyFirst") in names and ("joined", "PyLate") in names and ("left", "PyFirst") in names, names


def server_regex(name: str) -> str:
    """The regex Paparazzi's server binds for a telemetry message (`Tm_Pprz.message_bind`)."""
    return r"^([^ ]*) +(%s( .*|$))" % name


def test_f_virtual_copters_send_what_paparazzis_server_registers_them_with(twinswarm_bin, bus):
    server = Agent("Paparazzi server", bus)
    ids = {n: server.bind(server_regex(n)) for n in ["ALIVE", "INS_REF", "ROTORCRAFT_STATUS"]}
    server.start()
    try:
        proc = run_sim(twinswarm_bin, bus, 6.0)
        assert server.joined.wait(15)
        finish(proc)
    finally:
        server.stop()
    alive = [g for g in server.received(ids["ALIVE"]) if g[0] == "101"]
    assert len(alive) >= 2, alive
    md5 = alive[0][1].split(" ")[1].split(",")
    assert len(md5) == 16 and all(b == "0" for b in md5), alive[0]  # the server's "MD5 is ZERO" case
    ins_ref = [g for g in server.received(ids["INS_REF"]) if g[0] == "101"]
    assert ins_ref, "no INS_REF"
    x0, y0, z0, lat0, lon0 = (int(v) for v in ins_ref[0][1].split(" ")[1:6])
    assert abs((x0**2 + y0**2 + z0**2) ** 0.5 / 100 - 6.365e6) < 5e3  # cm, on the Earth's surface
    assert (lat0, lon0) == (521398600, 116454800)
    status = [g for g in server.received(ids["ROTORCRAFT_STATUS"]) if g[0] == "101"]
    assert status and len(status[-1][1].split(" ")) == 13, status[-1:]
