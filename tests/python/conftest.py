"""Shared fixtures and helpers: the twinswarm binary, free loopback ports, loopback-only Zenoh
client sessions, and the shared data directory (a loud skip, or a failure under CI=true, when
it is absent)."""
import json
import os
import pathlib
import socket
# Imported before any test: pytest's hook for unraisable exceptions imports it on first use, and
# when the garbage collector finalises a leaked socket (ivy-python never closes its UDP
# listener) in the middle of that first import, the hook fails on the half-initialised module
# and fails whichever test was running (seen in CI: test_py_envs). Imported here, a leak stays
# the warning it is.
import tracemalloc  # noqa: F401

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]

# The start of the reason of a test skipped for want of shared data (skip_for_absent_shared),
# by which the end of the session lists them (also from pytest-xdist's workers).
_ABSENT = " not found at "


@pytest.fixture(scope="session")
def twinswarm_bin() -> pathlib.Path:
    path = pathlib.Path(os.environ.get("TWINSWARM_BIN", ROOT / "target" / "debug" / "twinswarm"))
    if not path.exists():
        pytest.fail(f"twinswarm binary not found at {path}: build it with `cargo build -p twinswarm`")
    return path


def free_tcp_port() -> int:
    """A TCP port free on 127.0.0.1 right now (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def loopback_endpoint() -> str:
    """A Zenoh endpoint on 127.0.0.1 at a free port, for a simulator to listen on."""
    return f"tcp/127.0.0.1:{free_tcp_port()}"


@pytest.fixture
def free_port() -> int:
    return free_tcp_port()


def zenoh_client_config(endpoint: str):
    """A Zenoh configuration for a pure client on loopback: peer mode, listening nowhere,
    multicast scouting off, connecting only to `endpoint` (which must be on 127.0.0.1)."""
    import zenoh

    assert endpoint.split("/", 1)[-1].startswith("127.0.0.1:"), f"not a loopback endpoint: {endpoint}"
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    return conf


def under_ci() -> bool:
    """Whether the tests run under CI (CI=true or CI=1, as CI services set it)."""
    return os.environ.get("CI", "").lower() in ("true", "1")


def shared_data_dir() -> pathlib.Path:
    """$TWINSWARM_SHARED_DATA if set, else shared/data in the nearest ancestor of the repository
    that has one (normally the repository's ../shared/data), else that expected path."""
    if "TWINSWARM_SHARED_DATA" in os.environ:
        return pathlib.Path(os.environ["TWINSWARM_SHARED_DATA"])
    for d in ROOT.parents:
        if (d / "shared" / "data").is_dir():
            return d / "shared" / "data"
    return ROOT.parent / "shared" / "data"


def shared_data_or_skip(*parts: str) -> pathlib.Path:
    """The directory `parts` below the shared data directory. When it is absent: under CI=true
    the test fails, naming the path; otherwise it is skipped loudly (listed at the end of the
    session) and recorded as a line `test<TAB>path` in the file named by $TWINSWARM_SKIP_LOG,
    which scripts/test.sh counts."""
    path = shared_data_dir().joinpath(*parts)
    if path.is_dir():
        return path
    skip_for_absent_shared(path, "shared data", "TWINSWARM_SHARED_DATA")


def skip_for_absent_shared(path: pathlib.Path, what: str, env_var: str):
    """For a test that needs `path` of ../shared (`what` names it; `env_var` is the variable
    that can point elsewhere), which is absent: under CI=true the test fails, naming the path;
    otherwise it is skipped loudly (listed at the end of the session) and recorded as a line
    `test<TAB>path` in the file named by $TWINSWARM_SKIP_LOG, which scripts/test.sh counts."""
    test = os.environ.get("PYTEST_CURRENT_TEST", "?").rsplit(" (", 1)[0]
    how = f"from {env_var}" if env_var in os.environ else f"{env_var} unset"
    if under_ci():
        pytest.fail(f"{what} not found at {path} ({how}); CI=true, so this is a failure, not a skip "
                    f"(provide the directory or point {env_var} at it)", pytrace=False)
    log = os.environ.get("TWINSWARM_SKIP_LOG")
    if log:
        with open(log, "a", encoding="utf-8") as f:
            f.write(f"{test}\t{path}\n")
    pytest.skip(f"{what} not found at {path} ({how})")


def pytest_terminal_summary(terminalreporter):
    # From the skip reports, not from a list kept here: under pytest-xdist the skips happen in
    # the workers and only their reports reach this process.
    absent = []
    for rep in terminalreporter.stats.get("skipped", []):
        reason = rep.longrepr[2] if isinstance(rep.longrepr, (tuple, list)) else ""
        reason = reason.removeprefix("Skipped: ")
        if _ABSENT in reason:
            absent.append(f"SKIPPED {rep.nodeid}: {reason.rsplit(' (', 1)[0]}")
    if absent:
        terminalreporter.section("shared data absent", sep="=", yellow=True, bold=True)
        for line in absent:
            terminalreporter.write_line(line, yellow=True)


def pytest_configure(config):
    # The NPS tests (test_nps.py) build their aircraft into one Paparazzi tree and its private
    # conf: they must run one after another, in one process. pytest-xdist's `--dist loadfile`
    # (scripts/test.sh) keeps each file's tests on one worker; `load` would spread them.
    dist = getattr(config.option, "dist", "no")
    if getattr(config.option, "numprocesses", None) and dist not in ("no", "loadfile", "loadscope"):
        raise pytest.UsageError(f"tests/python under pytest-xdist needs --dist loadfile (not {dist}): "
                                "test_nps.py's tests share one Paparazzi tree")


def pytest_collection_modifyitems(config, items):
    """Under pytest-xdist (scripts/test.sh: `-n N --dist loadfile --no-loadscope-reorder`), the
    NPS tests first: together they are the longest file of the session, so one worker starts
    on them while the others take the rest, file by file. Without xdist the order is left as
    collected."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        items[:] = [i for i in items if i.path.name == "test_nps.py"] + [i for i in items if i.path.name != "test_nps.py"]


# ---- the real Paparazzi ground segment (pprz_ground.py) ----

@pytest.fixture
def paparazzi_ground(tmp_path):
    """A factory for the real Paparazzi `link` and `server` (built from ../shared/paparazzi;
    a loud skip, or a failure under CI=true, without it):

        g = paparazzi_ground(messages_xml=None, aircraft=None, link=True, server=True,
                             server_log=False)

    starts them on a private loopback Ivy bus (g.bus, 127.255.255.255:<free port>) with a
    private PAPARAZZI_HOME (g.home) whose var/messages.xml is `messages_xml` (default: the
    build's pprzlink v1.0 one) and whose conf.xml has `aircraft` (pprz_ground.Aircraft; default
    Virtual_201/202 as 201/202, registrable), and returns a pprz_ground.GroundSegment once both
    have joined the bus: g.agent (an ivy-python agent on the bus: bind, received, send via
    g.send), g.link_port (link's UDP port, where aircraft frames go), g.uplink_port and
    g.uplink (the UDP socket on 127.0.0.1 where link sends frames for aircraft; see
    g.send_downlink, g.keep_alive, g.recv_uplink), g.log('link'|'server'). Stopped at teardown;
    their output is printed then (shown for a failing test)."""
    import pprz_ground

    started = []

    def start(messages_xml=None, **kwargs):
        g = pprz_ground.start_ground_segment(tmp_path / f"ground{len(started)}", messages_xml, **kwargs)
        started.append(g)
        return g

    yield start
    for g in started:
        g.stop()
        for which in g.logs:
            print(f"---- {which} ({g.bus}) ----\n{g.log(which)[-4000:]}")


@pytest.fixture(scope="session")
def lab_messages_xml(tmp_path_factory):
    """A FINken lab's messages.xml for today's Paparazzi: pprzlink v1.0 with the FINken
    telemetry and SONAR_UPLINK (datalink 153) merged in (pprz_ground.lab_messages_xml), from
    ../shared/data/paparazzi_finken."""
    import pprz_ground

    finken = shared_data_or_skip("paparazzi_finken")
    return pprz_ground.lab_messages_xml(tmp_path_factory.mktemp("lab_messages"), finken)


# ---- reading logs ----

def proto_to_dict(m):
    """A protobuf message as a dict with its field names and native values: lists for repeated
    fields, None for an absent optional field or message, dicts for google.protobuf.Struct.
    Logs of before protobuf were JSON with the same field names, so tests read both alike."""
    from google.protobuf import json_format

    out = {}
    for f in m.DESCRIPTOR.fields:
        v = getattr(m, f.name)
        if f.message_type is not None and f.message_type.full_name == "google.protobuf.Struct":
            out[f.name] = json_format.MessageToDict(v) if m.HasField(f.name) else None
        elif f.is_repeated:
            out[f.name] = [proto_to_dict(x) for x in v] if f.message_type is not None else list(v)
        elif f.has_presence and not m.HasField(f.name):
            out[f.name] = None
        elif f.message_type is not None:
            out[f.name] = proto_to_dict(v)
        else:
            out[f.name] = v
    return out


def log_messages(path, topics=None):
    """(channel, message, body) for every message of a log in file order, CRCs validated,
    `body` decoded with the file's own schemas (protobuf through PyPI mcap-protobuf-support;
    JSON for logs written before) as a dict (see proto_to_dict)."""
    from google.protobuf.unknown_fields import UnknownFieldSet
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    factory = DecoderFactory()
    decoders = {}
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        for schema, channel, message in reader.iter_messages(topics=topics, log_time_order=False):
            if channel.message_encoding == "json":
                yield channel, message, json.loads(message.data)
                continue
            assert channel.message_encoding == "protobuf", channel
            if schema.id not in decoders:
                decoders[schema.id] = factory.decoder_for(channel.message_encoding, schema)
            proto = decoders[schema.id](message.data)
            assert len(UnknownFieldSet(proto)) == 0, f"{channel.topic}: fields its schema does not declare"
            yield channel, message, proto_to_dict(proto)


def log_bodies(path, topic):
    """The decoded bodies of every message on `topic`."""
    return [body for _c, _m, body in log_messages(path, [topic])]
