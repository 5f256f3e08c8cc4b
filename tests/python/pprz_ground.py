"""The real Paparazzi ground segment (`link`, `server`) for the tests: where the build is, a
private Paparazzi home per test, messages.xml merging, starting `link` and `server` on a private
loopback Ivy bus, and pprzlink frames on `link`'s UDP side.

The build comes from ../shared/paparazzi/build.sh into target/paparazzi (scripts/test.sh runs
it; `paparazzi_or_skip` runs it too when it is missing). With neither that build nor
../shared/paparazzi the tests skip loudly (a line in $TWINSWARM_SKIP_LOG), or fail under CI=true.

How `link` and `server` find their files (read in sw/ground_segment/tmtc/{link,server}.ml,
sw/lib/ocaml/env.ml and pprzlink's lib/v2.0/ocaml/pprzLink.ml of the build):
- the pprzlink library of both reads `$PPRZLINK_DIR/messages.xml` (and `units.xml`), else
  `$PAPARAZZI_HOME/var/messages.xml`; the file is parsed when first used, at start-up. Its
  `<!DOCTYPE protocol SYSTEM "messages.dtd">` is resolved beside it: `messages.dtd` must be there.
  There is no command-line flag for it.
- `server` reads `$PAPARAZZI_HOME/conf/conf.xml` at start-up, and, when an aircraft's first
  `ALIVE` arrives, `$PAPARAZZI_HOME/var/aircrafts/<name>/flight_plan.xml` (a `<dump>` holding a
  `<flight_plan>`), `…/conf/<airframe>` and `…/conf/aircraft.md5`, and decodes that aircraft's
  telemetry with `$PAPARAZZI_HOME/var/messages.xml` (always that path, whatever PPRZLINK_DIR
  says).
So each ground segment here gets its own PAPARAZZI_HOME, a temporary directory holding only
those files; the programs themselves run from the build.
"""
import os
import pathlib
import shutil
import socket
import subprocess
import sys
import threading
import time
import warnings
from dataclasses import dataclass, field

import pytest

from conftest import ROOT, skip_for_absent_shared

BUILD_DIR = pathlib.Path(os.environ.get("TWINSWARM_PAPARAZZI_BUILD", ROOT / "target" / "paparazzi"))

# The arena origin of Twinswarm's virtual copters (crates/bridge/src/paparazzi/convert.rs,
# ARENA_ORIGIN_LLA), which their INS_REF carries.
ARENA_LAT0 = 52.13986
ARENA_LON0 = 11.64548

# docs/paparazzi_ground.md: the flight plan a lab adds so the GCS map agrees with INS_REF.
ARENA_FLIGHT_PLAN = f"""<flight_plan name="Twinswarm arena" lat0="{ARENA_LAT0}" lon0="{ARENA_LON0}" alt="50.8"
             ground_alt="50" security_height="0.3" max_dist_from_home="10">
  <waypoints>
    <waypoint name="HOME" x="0.0" y="0.0"/>
    <waypoint name="NE" x="2.0" y="1.5"/>
    <waypoint name="SW" x="-2.0" y="-1.5"/>
  </waypoints>
  <blocks>
    <block name="Fly">
      <stay wp="HOME"/>
    </block>
  </blocks>
</flight_plan>"""


# The airframe copy `server` reads for a registered aircraft: it needs the BAT section (its
# battery alerts look it up every second, and fail without it); the rest is unused.
AIRFRAME = """<airframe name="{name}">
  <section name="BAT">
    <define name="CATASTROPHIC_BAT_LEVEL" value="9.3" unit="V"/>
    <define name="CRITIC_BAT_LEVEL" value="9.6" unit="V"/>
    <define name="LOW_BAT_LEVEL" value="10.1" unit="V"/>
    <define name="MAX_BAT_LEVEL" value="12.4" unit="V"/>
  </section>
</airframe>
"""


def shared_paparazzi_dir() -> pathlib.Path:
    """$TWINSWARM_SHARED_PAPARAZZI if set, else shared/paparazzi in the nearest ancestor of the
    repository that has one (normally ../shared/paparazzi), else that expected path."""
    if "TWINSWARM_SHARED_PAPARAZZI" in os.environ:
        return pathlib.Path(os.environ["TWINSWARM_SHARED_PAPARAZZI"])
    for d in ROOT.parents:
        if (d / "shared" / "paparazzi" / "build.sh").is_file():
            return d / "shared" / "paparazzi"
    return ROOT.parent / "shared" / "paparazzi"


def build_finished(build_dir: pathlib.Path = BUILD_DIR) -> bool:
    """build.sh writes WORK_DIR/.built (the tarball's hash) last, after checking that `link` and
    `server` exist; a second run with the same tarball keeps the build and exits at once."""
    tmtc = build_dir / "paparazzi" / "sw" / "ground_segment" / "tmtc"
    return (build_dir / ".built").is_file() and all(os.access(tmtc / p, os.X_OK) for p in ("link", "server"))


@dataclass
class Paparazzi:
    """A finished build: where its programs are and the environment they need."""

    build_dir: pathlib.Path
    env: dict

    @property
    def home(self) -> pathlib.Path:
        return self.build_dir / "paparazzi"

    @property
    def tmtc(self) -> pathlib.Path:
        return self.home / "sw" / "ground_segment" / "tmtc"

    @property
    def pprzlink_python(self) -> pathlib.Path:
        """pprzlink's Python library (protocol 2.0) as the build installed it."""
        return self.home / "var" / "lib" / "python"

    @property
    def messages_xml(self) -> pathlib.Path:
        """The build's own messages.xml (pprzlink's message_definitions/v1.0)."""
        return self.home / "var" / "messages.xml"


def _env_of(build_dir: pathlib.Path) -> dict:
    """The environment of build_dir/env.sh (sourced in bash), on top of this process's."""
    out = subprocess.run(
        ["bash", "-c", f'. "{build_dir}/env.sh" && env -0'], check=True, capture_output=True
    ).stdout
    env = dict(item.split("=", 1) for item in out.decode().split("\0") if "=" in item)
    env.pop("PPRZLINK_DIR", None)
    return env


_PAPARAZZI = None


def paparazzi_or_skip() -> Paparazzi:
    """The Paparazzi build in target/paparazzi, built first with ../shared/paparazzi/build.sh
    when it is not finished (build.sh keeps a finished build). With neither a finished build nor
    ../shared/paparazzi: a loud skip (a line in $TWINSWARM_SKIP_LOG), or a failure under
    CI=true."""
    global _PAPARAZZI
    if _PAPARAZZI is not None:
        return _PAPARAZZI
    if not build_finished():
        src = shared_paparazzi_dir()
        if not (src / "build.sh").is_file():
            skip_for_absent_shared(src, "the Paparazzi source (shared/paparazzi/build.sh)",
                                   "TWINSWARM_SHARED_PAPARAZZI")
        t0 = time.monotonic()
        r = subprocess.run(["bash", str(src / "build.sh"), str(BUILD_DIR)], capture_output=True, text=True)
        if r.returncode != 0 or not build_finished():
            pytest.fail(f"{src}/build.sh {BUILD_DIR} failed ({r.returncode}) after "
                        f"{time.monotonic() - t0:.0f} s:\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}", pytrace=False)
    _PAPARAZZI = Paparazzi(BUILD_DIR, _env_of(BUILD_DIR))
    return _PAPARAZZI


# ---- messages.xml ----

def merge_messages(base: pathlib.Path, extra: pathlib.Path, names: dict, out: pathlib.Path) -> pathlib.Path:
    """Writes to `out` the messages.xml `base` (pprzlink v1.0 format, classes with ids) with
    the messages `names` ({class name: [message name, …]}) taken from `extra` (any format, e.g.
    the pre-pprzlink FINken conf/messages.xml whose classes have no id): a message of `base`
    with the same name, or with the same id in the same class, is replaced (ids must stay
    unique in a class: pprzlink's OCaml library fails on a duplicate, its Python library keeps
    the last). The ids are `extra`'s, the ones the FINken firmware was built with. Returns
    `out`, with messages.dtd copied beside it. Which messages were displaced is in
    `out.with_suffix('.replaced.txt')`."""
    from lxml import etree

    tree = etree.parse(str(base))
    src = etree.parse(str(extra))
    replaced = []
    for class_name, msg_names in names.items():
        (cls,) = tree.xpath(f"//msg_class[@name='{class_name}']")
        for name in msg_names:
            found = src.xpath(f"//msg_class[@name='{class_name}']/message[@name='{name}']")
            assert len(found) == 1, f"{extra}: {class_name}/{name} found {len(found)} times"
            new = found[0]
            for old in cls.xpath("message"):
                if old.get("name") == name or int(old.get("id"), 0) == int(new.get("id"), 0):
                    replaced.append(f"{class_name} {old.get('id')} {old.get('name')} -> {new.get('id')} {name}")
                    cls.remove(old)
            new = etree.fromstring(etree.tostring(new))
            new.tail = "\n\n    "
            cls.append(new)
    out.parent.mkdir(parents=True, exist_ok=True)
    tree.write(str(out), xml_declaration=True, encoding="UTF-8", doctype='<!DOCTYPE protocol SYSTEM "messages.dtd">')
    shutil.copy(base.parent / "messages.dtd", out.parent / "messages.dtd")
    out.with_suffix(".replaced.txt").write_text("\n".join(replaced) + "\n")
    return out


# ---- a private Paparazzi home ----

@dataclass
class Aircraft:
    """An aircraft of the private conf.xml; `built` makes the var/aircrafts/<name>/ files that
    `server` needs to register it (what building the aircraft once leaves there)."""

    name: str
    ac_id: int
    built: bool = True
    md5: str = "00112233445566778899aabbccddeeff"


def make_home(root: pathlib.Path, pprz: Paparazzi, messages_xml: pathlib.Path, aircraft: list) -> pathlib.Path:
    """A private PAPARAZZI_HOME under `root` for `link` and `server`: var/messages.xml (with
    messages.dtd and units.xml beside it), conf/conf.xml with `aircraft`, the arena's flight plan,
    and for each built aircraft var/aircrafts/<name>/{flight_plan.xml, conf/<airframe>,
    conf/aircraft.md5}."""
    home = root / "paparazzi_home"
    (home / "var").mkdir(parents=True)
    (home / "conf" / "flight_plans").mkdir(parents=True)
    shutil.copy(messages_xml, home / "var" / "messages.xml")
    dtd = messages_xml.parent / "messages.dtd"
    shutil.copy(dtd if dtd.is_file() else pprz.home / "var" / "messages.dtd", home / "var" / "messages.dtd")
    shutil.copy(pprz.home / "var" / "units.xml", home / "var" / "units.xml")
    (home / "var" / "logs").mkdir()
    airframe = "airframes/twinswarm/virtual_finken.xml"
    entries = []
    for ac in aircraft:
        entries.append(
            f'  <aircraft name="{ac.name}" ac_id="{ac.ac_id}" airframe="{airframe}" radio="radios/spektrum.xml"\n'
            f'   telemetry="telemetry/default_rotorcraft.xml" flight_plan="flight_plans/twinswarm_arena.xml"\n'
            f'   settings="settings/rotorcraft_basic.xml" settings_modules="" gui_color="blue"/>'
        )
        if ac.built:
            d = home / "var" / "aircrafts" / ac.name
            (d / "conf" / "airframes" / "twinswarm").mkdir(parents=True)
            (d / "flight_plan.xml").write_text(
                "<dump>\n" + ARENA_FLIGHT_PLAN + '\n<stages><stage block="0" block_name="Fly" stage="0">'
                '<stay wp="HOME"/></stage></stages>\n</dump>\n'
            )
            (d / "conf" / airframe).write_text(AIRFRAME.format(name=ac.name))
            (d / "conf" / "aircraft.md5").write_text(ac.md5 + "\n")
    (home / "conf" / "conf.xml").write_text("<conf>\n" + "\n".join(entries) + "\n</conf>\n")
    # The airframe, and the build's radios, telemetry, settings and modules, for what server
    # reads of every aircraft of conf.xml when it writes its log (without -n).
    (home / "conf" / airframe).parent.mkdir(parents=True)
    (home / "conf" / airframe).write_text(AIRFRAME.format(name="Twinswarm virtual FINken"))
    for d in ("radios", "telemetry", "settings", "modules", "firmwares", "boards", "autopilot"):
        if (pprz.home / "conf" / d).exists():
            (home / "conf" / d).symlink_to(pprz.home / "conf" / d)
    (home / "conf" / "flight_plans" / "twinswarm_arena.xml").write_text(ARENA_FLIGHT_PLAN + "\n")
    return home


# ---- ports ----

def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def loopback_bus() -> str:
    """A private Ivy bus: the loopback broadcast address and a free UDP port."""
    return f"127.255.255.255:{free_udp_port()}"


# ---- pprzlink frames (the aircraft side of `link`) ----

_PPRZLINK_LOCK = threading.Lock()
_PPRZLINK_LOADED = None


def pprzlink(messages_xml: pathlib.Path):
    """pprzlink's own Python library (protocol 2.0, from the build's var/lib/python), loaded with
    `messages_xml`. Its message tables are module-wide: the last file loaded decides."""
    global _PPRZLINK_LOADED
    pprz = paparazzi_or_skip()
    path = str(pprz.pprzlink_python)
    with _PPRZLINK_LOCK:
        if path not in sys.path:
            sys.path.insert(0, path)
        with warnings.catch_warnings():  # its regexes have invalid escapes ('[\\[\\]]')
            warnings.simplefilter("ignore", DeprecationWarning)
            warnings.simplefilter("ignore", SyntaxWarning)
            import pprzlink.message
            import pprzlink.pprz_transport
            from pprzlink import messages_xml_map

        key = str(pathlib.Path(messages_xml).resolve())
        if _PPRZLINK_LOADED != key:
            for name in dir(messages_xml_map):
                if name.startswith("message_dictionary"):
                    getattr(messages_xml_map, name).clear()
            messages_xml_map.parse_messages(key)
            _PPRZLINK_LOADED = key
    return pprzlink


@dataclass
class UplinkFrame:
    """One pprzlink 2.0 frame `link` sent towards an aircraft, decoded by pprzlink's Python
    library: header and the message with its fields by name."""

    raw: bytes
    sender_id: int
    receiver_id: int
    component_id: int
    class_id: int
    msg_class: str
    name: str
    fields: dict


# ---- the ground segment ----

@dataclass
class GroundSegment:
    """`link` and/or `server` running on a private loopback Ivy bus with a private
    PAPARAZZI_HOME. `agent` is an ivy-python agent on that bus (started before them) that tests
    use to send and receive texts. `uplink` is the UDP socket playing the aircraft side of
    `link`: frames sent from it reach `link -udp` on `link_port`, and `link` sends its uplink
    to this socket's address at `uplink_port`."""

    bus: str
    home: pathlib.Path
    messages_xml: pathlib.Path
    agent: object
    link_port: int | None
    uplink_port: int | None
    uplink: socket.socket | None
    procs: dict = field(default_factory=dict)
    logs: dict = field(default_factory=dict)
    _heartbeats: list = field(default_factory=list)
    _pong_lock: threading.Condition = field(default_factory=threading.Condition)
    _pongs: set = field(default_factory=set)

    def log(self, which: str) -> str:
        """What `link` or `server` has printed so far (stdout and stderr)."""
        return self.logs[which].read_text(errors="replace") if which in self.logs else ""

    def server_data_log(self) -> str:
        """What `server` logged (started with server_log=True): one line per message it decoded."""
        return "".join(p.read_text(errors="replace") for p in sorted((self.home / "var" / "logs").glob("*.data")))

    def alive(self) -> dict:
        return {k: p.poll() is None for k, p in self.procs.items()}

    def sync(self, timeout_s: float = 10.0):
        """Pings `link` and `server` from the agent and waits for their Pongs. Ivy agents handle a
        connection's lines in order, so afterwards each has taken in every regex the agent bound
        before: call it after binding and before starting what they should see (else a text sent
        meanwhile, e.g. the NEW_AIRCRAFT of an early ALIVE, can miss the new regex)."""
        names = [n for k, n in (("link", "Link"), ("server", "Paparazzi server")) if k in self.procs]
        with self._pong_lock:
            self._pongs.clear()
            for name in names:
                for c in self.agent.server.get_client_with_name(name):
                    c.send_ping()
            ok = self._pong_lock.wait_for(lambda: all(n in self._pongs for n in names), timeout_s)
        assert ok, f"no Pong from {[n for n in names if n not in self._pongs]} within {timeout_s} s"

    def _on_pong(self, client, _delta):
        with self._pong_lock:
            self._pongs.add(client.agent_name)
            self._pong_lock.notify_all()

    def send(self, text: str) -> int:
        """Sends an Ivy text from the agent; returns how many peer regexes matched it."""
        return self.agent.server.send_msg(text)

    # the aircraft side of link
    def send_downlink(self, ac_id: int, name: str, values=(), msg_class: str = "telemetry"):
        """Sends one telemetry message as aircraft `ac_id`, a pprzlink 2.0 frame made by
        pprzlink's Python library, to `link`'s UDP port (which makes the aircraft live for
        `link`, and its address the one `link` sends the uplink to)."""
        pl = pprzlink(self.messages_xml)
        msg = pl.message.PprzMessage(msg_class, name)
        msg.set_values(list(values))
        frame = pl.pprz_transport.PprzTransport(msg_class).pack_pprz_msg(ac_id, msg)
        self.uplink.sendto(frame, ("127.0.0.1", self.link_port))

    def keep_alive(self, ac_id: int, period_s: float = 1.0):
        """Sends ALIVE (zero md5) as aircraft `ac_id` now and every `period_s` until stop():
        `link` forwards datalink messages only to aircraft heard within its -ac_timeout
        (5 s by default)."""
        stop = threading.Event()
        md5 = [0] * 16

        def beat():
            while not stop.is_set():
                self.send_downlink(ac_id, "ALIVE", [md5])
                stop.wait(period_s)

        self.send_downlink(ac_id, "ALIVE", [md5])
        t = threading.Thread(target=beat, daemon=True)
        t.start()
        self._heartbeats.append((stop, t))

    def recv_uplink(self, timeout_s: float, count: int = 1, name: str | None = None) -> list:
        """Frames `link` sent towards the aircraft (PING every 5 s among them), decoded, until
        `count` frames (named `name`, if given) arrived or `timeout_s` passed."""
        pl = pprzlink(self.messages_xml)
        got = []
        deadline = time.monotonic() + timeout_s
        while len([f for f in got if name is None or f.name == name]) < count:
            left = deadline - time.monotonic()
            if left <= 0:
                break
            self.uplink.settimeout(left)
            try:
                data, _addr = self.uplink.recvfrom(4096)
            except socket.timeout:
                break
            parser = pl.pprz_transport.PprzTransport("datalink")
            for b in data:
                if parser.parse_byte(bytes([b])):
                    sender, receiver, component, msg = parser.unpack()
                    got.append(UplinkFrame(data, sender, receiver, component, msg.class_id, msg.msg_class,
                                           msg.name, dict(zip(msg.fieldnames, msg.fieldvalues))))
        return got

    def stop(self):
        for stop, t in self._heartbeats:
            stop.set()
            t.join(timeout=3)
        for p in self.procs.values():
            if p.poll() is None:
                p.terminate()
        for p in self.procs.values():
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(timeout=5)
        self.agent.stop()
        if self.uplink is not None:
            self.uplink.close()


def _wait_initialized(agent, name: str, proc: subprocess.Popen, log: pathlib.Path, timeout_s: float):
    """Waits until `name` has connected to `agent` and sent all its regexes (EndRegexp)."""
    from ivy.ivy import INITIALIZED

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"{name} exited ({proc.returncode}): {log.read_text(errors='replace')[-3000:]}")
        clients = agent.server.get_client_with_name(name)
        if clients and all(c.status == INITIALIZED for c in clients):
            return
        time.sleep(0.05)
    raise RuntimeError(f"{name} did not join the bus within {timeout_s} s: {log.read_text(errors='replace')[-3000:]}")


def start_ground_segment(tmp_path: pathlib.Path, messages_xml: pathlib.Path | None = None,
                         aircraft: list | None = None, link: bool = True, server: bool = True,
                         agent_name: str = "PyGround", link_args=(), server_args=(),
                         server_log: bool = False, join_timeout_s: float = 15.0) -> GroundSegment:
    """Starts `link -udp` and `server -n` of the Paparazzi build on a private bus
    (127.255.255.255:<free port>) with a private PAPARAZZI_HOME (messages.xml: `messages_xml`,
    default the build's pprzlink v1.0 one; conf.xml: `aircraft`, default Virtual_201/202 as
    ac_id 201/202, built) and an ivy-python agent, and waits until both have joined the bus
    (each has sent the agent all its regexes, and answered a Ping: see .sync). `server_log`: let `server` write its log
    (home/var/logs/*.data: every message it decoded, `<time> <ac_id> <NAME> <values>`) instead
    of `-n`. Call .stop() at the end (the `paparazzi_ground` fixture does)."""
    from test_ivy import Agent  # test_ivy.py's ivy-python agent: bind(regex), received(id), stop()

    pprz = paparazzi_or_skip()
    messages_xml = pathlib.Path(messages_xml or pprz.messages_xml)
    if aircraft is None:
        aircraft = [Aircraft("Virtual_201", 201), Aircraft("Virtual_202", 202)]
    home = make_home(tmp_path, pprz, messages_xml, aircraft)
    env = dict(pprz.env, PAPARAZZI_HOME=str(home))
    env.pop("PPRZLINK_DIR", None)
    bus = loopback_bus()
    agent = Agent(agent_name, bus).start()
    uplink = None
    g = GroundSegment(bus, home, home / "var" / "messages.xml", agent, None, None, None)
    agent.server.bind_pong(g._on_pong)
    try:
        if link:
            uplink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            uplink.bind(("127.0.0.1", 0))
            g.uplink, g.uplink_port = uplink, uplink.getsockname()[1]
            g.link_port = free_udp_port()
            g.logs["link"] = tmp_path / "link.log"
            cmd = [str(pprz.tmtc / "link"), "-b", bus, "-udp", "-udp_port", str(g.link_port),
                   "-udp_uplink_port", str(g.uplink_port), *link_args]
            with open(g.logs["link"], "wb") as out:
                g.procs["link"] = subprocess.Popen(cmd, env=env, cwd=tmp_path, stdin=subprocess.DEVNULL,
                                                   stdout=out, stderr=subprocess.STDOUT)
        if server:
            g.logs["server"] = tmp_path / "server.log"
            cmd = [str(pprz.tmtc / "server"), "-b", bus, *([] if server_log else ["-n"]),
                   "-udp_json_stream_disable", *server_args]
            with open(g.logs["server"], "wb") as out:
                g.procs["server"] = subprocess.Popen(cmd, env=env, cwd=tmp_path, stdin=subprocess.DEVNULL,
                                                     stdout=out, stderr=subprocess.STDOUT)
        for key, name in (("link", "Link"), ("server", "Paparazzi server")):
            if key in g.procs:
                _wait_initialized(agent, name, g.procs[key], g.logs[key], join_timeout_s)
        g.sync(join_timeout_s)
    except BaseException:
        g.stop()
        raise
    return g


# ---- a lab's messages.xml ----

# The FINken telemetry of FINken_conf_messages.xml (ovgu-FINken/paparazzi, the FINken branch's
# conf/messages.xml): what a FINken and Twinswarm's virtual copters send that pprzlink lacks,
# and ROTORCRAFT_STATUS in the FINken-era layout they send (12 fields; pprzlink v1.0 has 14).
FINKEN_TELEMETRY = [
    "ROTORCRAFT_STATUS", "SONAR_ARRAY", "FINKEN_SENSOR_MODEL", "FINKEN_WALL_AVOID",
    "FINKEN_SYSTEM_SET_POINT", "FINKEN_ACTUATORS_SET_POINT", "FINKEN_ACTUATORS_MODEL", "FINKEN_IR_ADC",
]
# The mixed-reality firmware's uplink (mixed_reality_conf_messages.xml): datalink id 153,
# link="forwarded"; ac_id uint8, unused uint8, front, left, back, right uint16.
MIXED_REALITY_DATALINK = ["SONAR_UPLINK"]


def lab_messages_xml(out_dir: pathlib.Path, finken_dir: pathlib.Path) -> pathlib.Path:
    """A FINken lab's messages.xml for today's `link` and `server`: the build's pprzlink v1.0
    messages.xml with FINKEN_TELEMETRY from `finken_dir`/FINken_conf_messages.xml and
    SONAR_UPLINK from `finken_dir`/mixed_reality_conf_messages.xml merged in, at the FINken ids.
    Upstream messages they displace (same id): see `out_dir`/messages.replaced.txt."""
    pprz = paparazzi_or_skip()
    step = merge_messages(pprz.messages_xml, finken_dir / "FINken_conf_messages.xml",
                          {"telemetry": FINKEN_TELEMETRY}, out_dir / "step" / "messages.xml")
    out = merge_messages(step, finken_dir / "mixed_reality_conf_messages.xml",
                         {"datalink": MIXED_REALITY_DATALINK}, out_dir / "messages.xml")
    replaced = step.with_suffix(".replaced.txt").read_text() + out.with_suffix(".replaced.txt").read_text()
    out.with_suffix(".replaced.txt").write_text(replaced)
    return out
