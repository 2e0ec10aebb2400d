"""Property-based fuzzing (Hypothesis) of every input a user or an attacker controls (issue 13).

Inputs: recorded sessions (index, manifest, frame files, symlinks, timestamps), configuration files and
``--set``, source URLs, the serial IMU's line protocol, bundle.json and the relight inputs, and HTTP
requests to the MJPEG server.

The property everywhere: the call ends within a bounded time with either a result or one clean error
(an :class:`~illuminet.runtime.errors.IllumiNetError`; from the command line one ``illuminet:`` line
and exit status 1 or 2), never a traceback, a hang or a crash of the whole stream; committed data is
never lost (one damaged frame costs at most that frame).

Budgets: every test runs a few examples in the default suite (the ``quick`` parameter; the file takes
~20 s here) and :data:`THOROUGH` times as many under ``-m slow`` (``thorough``). The Hypothesis
profiles registered in ``tests/conftest.py`` set ``deadline=None`` (a shared machine's timings are
no property; the bounds below are generous wall-clock limits instead). A failure prints the smallest
example that shows it; ``--hypothesis-seed`` replays a run.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import math
import shutil
import socket
import struct
import threading
import time
import zlib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from illuminet.cli import main
from illuminet.runtime import config as C
from illuminet.runtime.errors import IllumiNetError

from ._sessions import make_session

#: examples in the thorough (``-m slow``) run per example of the quick one
THOROUGH = 25
BUDGETS = [
    pytest.param(1, id="quick"),
    pytest.param(THOROUGH, id="thorough", marks=[pytest.mark.slow, pytest.mark.timeout(3600)]),
]

# an exception in a server or decoder thread is a crash of the stream even when the call returns
pytestmark = pytest.mark.filterwarnings("error::pytest.PytestUnhandledThreadExceptionWarning")


def fuzz(n: int, budget: int):
    """Settings for ``n * budget`` examples (the profile's deadline and health checks otherwise)."""
    return settings(
        max_examples=n * budget,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much],
    )


class _ExcInfoRecords(logging.Handler):
    """Collects log records that carry a traceback at WARNING or above (a traceback on the user's terminal)."""

    def __init__(self):
        super().__init__(logging.WARNING)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.exc_info:
            self.records.append(record)


def cli(argv: list[str], limit_s: float = 60.0) -> tuple[int, str, str]:
    """Run ``illuminet ARGV`` in this process: (exit status, stdout, stderr), checked to be clean.

    Clean: it ended within ``limit_s``; no traceback was printed or logged; a failure (exit status 1
    or 2) printed exactly one ``illuminet:`` line, or argparse's usage line and its ``error:`` line.
    """
    out, err = io.StringIO(), io.StringIO()
    handler = _ExcInfoRecords()
    logging.getLogger().addHandler(handler)
    t0 = time.monotonic()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                rc = main(argv)
            except SystemExit as e:  # argparse: a flag it cannot parse
                rc = e.code if isinstance(e.code, int) else 2
    finally:
        logging.getLogger().removeHandler(handler)
    elapsed = time.monotonic() - t0
    o, e = out.getvalue(), err.getvalue()
    assert elapsed < limit_s, f"{argv}: took {elapsed:.1f} s"
    assert "Traceback" not in o + e, f"{argv}:\n{e}"
    assert not handler.records, f"{argv}: logged a traceback: {handler.records[0].getMessage()}"
    assert rc in (0, 1, 2), (argv, rc)
    if rc:
        lines = [ln for ln in e.splitlines() if ln.startswith("illuminet")]
        usage = "error:" in e and "usage:" in e
        # `replay --check` reports a damaged session on stdout, ending in "N problem(s)", with exit status 1
        report = "--check" in argv and rc == 1 and not lines and o.rstrip().endswith("problem(s)")
        assert len(lines) == 1 or (usage and not lines) or report, f"{argv}: rc {rc} but stderr is\n{e}"
    return rc, o, e


# ------------------------------------------------------------------------------- shared strategies

json_scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.sampled_from([0, -1, 1, 2**31, 2**63 - 1, 2**63, 2**64, 10**30]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 1e-300, 1e300, float("nan"), float("inf")]),
    st.text(max_size=30),
    st.sampled_from(["", ".", "..", "../x", "/etc/passwd", "frames/000000.png", "\x00", "a" * 300]),
)
json_values = st.recursive(
    json_scalars,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=10), inner, max_size=4),
    max_leaves=12,
)


def _png_header(w: int, h: int) -> bytes:
    chunk = b"IHDR" + struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + chunk + struct.pack(">I", zlib.crc32(chunk))


# ------------------------------------------------------------------------------------ sessions

N_FRAMES = 4
INDEX_KEYS = ["i", "seq", "t_device_ns", "t_host_ns", "color", "color_bytes", "depth", "depth_bytes", "exposure",
              "gravity", "imu", "intrinsics"]  # fmt: skip
MANIFEST_KEYS = ["format", "version", "width", "height", "intrinsics", "color", "depth", "index", "finalized",
                 "frame_count", "source"]  # fmt: skip

frame_no = st.integers(0, N_FRAMES - 1)
file_actions = st.one_of(
    st.tuples(st.just("truncate"), st.integers(0, 200)),
    st.tuples(st.just("garbage"), st.binary(max_size=64)),
    st.tuples(st.just("header"), st.integers(0, 2**32 - 1), st.integers(0, 2**32 - 1)),
    st.sampled_from([("loop",), ("outside",), ("dir",), ("delete",), ("to_dir",), ("flip",)]),
)
session_mutations = st.one_of(
    st.tuples(st.just("index_set"), frame_no, st.sampled_from(INDEX_KEYS) | st.text(max_size=8), json_values),
    st.tuples(st.just("index_del"), frame_no, st.sampled_from(INDEX_KEYS)),
    st.tuples(st.just("index_line"), frame_no, st.binary(max_size=80)),
    st.tuples(st.just("timestamp"), frame_no, st.integers(-(2**65), 2**65) | st.sampled_from([0, 2**63 - 1, 2**62])),
    st.tuples(st.just("file"), frame_no, st.sampled_from(["color", "depth"]), file_actions),
    st.tuples(st.just("index_cut"), st.integers(0, 2000)),
    st.tuples(st.just("index_append"), st.binary(max_size=80)),
    st.tuples(
        st.just("manifest_set"),
        st.sampled_from(MANIFEST_KEYS + ["intrinsics.fx", "intrinsics.width", "color.encoding", "depth.scale"]),
        json_values,
    ),
    st.tuples(st.just("manifest_bytes"), st.binary(max_size=80)),
    st.tuples(st.just("manifest_link"), st.sampled_from(["outside", "loop", "dir"])),
)


def _mutate_session(s: Path, outside: Path, m: tuple) -> set[int] | None:
    """Apply one mutation; the frame numbers it may cost (None: the whole session, e.g. its manifest)."""
    try:
        return _apply(s, outside, m)
    except (OSError, ValueError):  # an earlier mutation made it impossible (a folder, a link loop, not JSON)
        return {m[1]} if m[0] in ("file", "index_set", "index_del", "timestamp", "index_line") else None


def _apply(s: Path, outside: Path, m: tuple) -> set[int] | None:
    index = s / "frames.jsonl"
    lines = index.read_bytes().split(b"\n")[:-1]
    kind = m[0]
    d = None
    if kind in ("index_set", "index_del", "timestamp", "index_line", "file"):
        if m[1] >= len(lines):
            return set()  # an earlier mutation cut the index before this line
        try:
            d = json.loads(lines[m[1]])
        except (ValueError, UnicodeDecodeError):
            pass
        if not isinstance(d, dict) and kind != "index_line":
            return {m[1]}  # an earlier mutation already damaged this line
    if kind in ("index_set", "index_del", "timestamp"):
        if kind == "index_set":
            d[m[2]] = m[3]
        elif kind == "index_del":
            d.pop(m[2], None)
        else:
            d["t_device_ns"] = m[2]
        lines[m[1]] = json.dumps(d).encode()
        index.write_bytes(b"\n".join(lines) + b"\n")
        return {m[1]}
    if kind == "index_line":
        lines[m[1]] = m[2]
        index.write_bytes(b"\n".join(lines) + b"\n")
        # new-line bytes split it into several lines (each one bad at most); the others keep their frames
        return {m[1]}
    if kind == "index_cut":
        data = index.read_bytes()
        index.write_bytes(data[: m[1]])
        return {k for k in range(N_FRAMES) if len(b"\n".join(lines[: k + 1])) + 1 > m[1]}
    if kind == "index_append":
        with open(index, "ab") as f:
            f.write(m[1])
        return set()
    if kind == "file":
        rel = d.get(m[2])
        if not isinstance(rel, str):
            return {m[1]}
        p = s / rel
        action = m[3]
        if action[0] == "truncate":
            p.write_bytes(p.read_bytes()[: action[1]])
        elif action[0] == "garbage":
            p.write_bytes((action[1] * (p.stat().st_size // max(len(action[1]), 1) + 1))[: p.stat().st_size])
        elif action[0] == "header":
            size = p.stat().st_size
            p.write_bytes((_png_header(action[1], action[2]) + b"\0" * size)[:size])
        elif action[0] == "loop":
            p.unlink()
            p.symlink_to(p.name)
        elif action[0] == "outside":
            p.unlink()
            p.symlink_to(outside)
        elif action[0] == "dir":
            p.unlink()
            p.mkdir()
        elif action[0] == "delete":
            p.unlink()
        elif action[0] == "to_dir":
            p.unlink()
            p.symlink_to(s)
        elif action[0] == "flip":
            b = bytearray(p.read_bytes())
            b[len(b) // 2] ^= 0xFF
            p.write_bytes(bytes(b))
        return {m[1]}
    mpath = s / "manifest.json"
    if kind == "manifest_set":
        d = json.loads(mpath.read_text())
        key = m[1]
        if "." in key:
            a, b = key.split(".", 1)
            if isinstance(d.get(a), dict):
                d[a][b] = m[2]
        else:
            d[key] = m[2]
        mpath.write_text(json.dumps(d))
    elif kind == "manifest_bytes":
        mpath.write_bytes(m[1])
    elif kind == "manifest_link":
        mpath.unlink()
        target = {"outside": outside, "loop": mpath, "dir": s}[m[1]]
        mpath.symlink_to(target if m[1] != "loop" else mpath.name)
    return None


@pytest.fixture(scope="module")
def session_template(tmp_path_factory) -> Path:
    base = tmp_path_factory.mktemp("fuzz-session")
    make_session(base / "template", N_FRAMES)
    (base / "outside.json").write_text(json.dumps({"format": "illuminet-session", "secret": 1}))
    return base


@pytest.mark.parametrize("budget", BUDGETS)
def test_fuzz_session_reader(session_template, budget):
    """Damaged sessions: a result or a SessionError; each damaged frame costs at most itself; no hang."""
    from illuminet.hw.replay import ReplaySource
    from illuminet.runtime.stage import EndOfStream
    from illuminet.runtime.stream.session import CorruptFrame, SessionReader

    counter = iter(range(10**9))

    @fuzz(30, budget)
    @given(st.lists(session_mutations, min_size=1, max_size=3))
    def prop(mutations):
        s = session_template / f"s{next(counter)}"
        shutil.copytree(session_template / "template", s, symlinks=True)
        try:
            cost: set[int] | None = set()
            for m in mutations:
                c = _mutate_session(s, session_template / "outside.json", m)
                cost = None if c is None or cost is None else cost | c
            t0 = time.monotonic()
            try:
                reader = SessionReader(s)
            except IllumiNetError:
                assert cost is None or cost, "an intact session was refused"
                return
            decoded = 0
            for k in range(len(reader)):
                try:
                    reader.read(k)
                    decoded += 1
                except CorruptFrame:
                    pass
            if cost is not None:  # committed data is never lost: at most the damaged frames are
                assert decoded >= N_FRAMES - len(cost), (mutations, reader.problems)
            problems = reader.check()
            assert all(isinstance(p, str) and "\n" not in p for p in problems)
            try:
                with ReplaySource(s, timing="asap") as src:  # the decoder threads: skip, never crash
                    n = sum(1 for _ in iter(src.read, None))
                assert n <= len(reader)
            except (IllumiNetError, EndOfStream):  # "no intact frame to replay" / "every frame ... unreadable"
                # (EndOfStream: the source's signal to the loop, which logs it and stops)
                assert decoded == 0 or len(reader) == 0
            assert time.monotonic() - t0 < 30
        finally:
            shutil.rmtree(s, ignore_errors=True)

    prop()


@pytest.mark.parametrize("budget", BUDGETS)
def test_fuzz_replay_check_and_recorded_timing_cli(session_template, budget):
    """``replay --check`` and a replay with recorded timing of a damaged session: one line, bounded time."""
    counter = iter(range(10**9))

    @fuzz(6, budget)
    @given(st.lists(session_mutations, min_size=1, max_size=2))
    def prop(mutations):
        s = session_template / f"c{next(counter)}"
        shutil.copytree(session_template / "template", s, symlinks=True)
        try:
            for m in mutations:
                _mutate_session(s, session_template / "outside.json", m)
            rc, out, _ = cli(["replay", str(s), "--check"], limit_s=30)
            assert rc in (0, 1) and (rc == 0) == out.rstrip().endswith("OK")
            # recorded timing through the source alone (the pipeline is fuzzed elsewhere): <= 4 frames
            # at 30 fps, whatever the timestamps say
            from illuminet.hw.replay import ReplaySource
            from illuminet.runtime.stage import EndOfStream

            t0 = time.monotonic()
            try:
                with ReplaySource(s, timing="recorded") as src:
                    while src.read() is not None:
                        pass
            except (IllumiNetError, EndOfStream):  # as in the asap test above: every frame unreadable
                pass
            assert time.monotonic() - t0 < 10
        finally:
            shutil.rmtree(s, ignore_errors=True)

    prop()


# ---------------------------------------------------------------------------- configuration

toml_scalars = st.one_of(
    st.booleans(),
    st.integers(min_value=-(2**63), max_value=2**63 - 1),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=20),
    st.sampled_from(["", " ", "0.0.0.0", "builtin:vase", "/nonexistent/x", "*", "egl", "usb"]),
)
toml_values = st.recursive(
    toml_scalars,
    lambda inner: st.lists(inner, max_size=10) | st.dictionaries(st.text(max_size=8), inner, max_size=3),
    max_leaves=12,
)
schema_keys = st.sampled_from([(s, k) for s, keys in C.SCHEMA.items() for k in keys])


def _toml(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, list):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    return "{" + ", ".join(f"{json.dumps(k, ensure_ascii=False)} = {_toml(x)}" for k, x in v.items()) + "}"


config_docs = st.dictionaries(
    st.sampled_from(list(C.SCHEMA)) | st.text(min_size=1, max_size=8),
    st.dictionaries(st.sampled_from([k for keys in C.SCHEMA.values() for k in keys]) | st.text(max_size=8),
                    toml_values, max_size=4),
    max_size=3,
)  # fmt: skip


def _toml_doc(doc: dict) -> str:
    out = []
    for section, keys in doc.items():
        out.append(f"[{json.dumps(section, ensure_ascii=False)}]")
        out += [f"{json.dumps(k, ensure_ascii=False)} = {_toml(v)}" for k, v in keys.items()]
    return "\n".join(out) + "\n"


def _assert_valid(cfg: C.Config) -> None:
    """Every value of a loaded configuration satisfies its schema (re-validating changes nothing)."""
    again = C.validate(cfg.to_dict(), "<re-validation>")
    assert again.to_dict() == cfg.to_dict()


@pytest.mark.parametrize("budget", BUDGETS)
def test_fuzz_config_files_and_set(tmp_path, budget):
    """Any config file or ``--set``: a valid Config or one ConfigError line with exit status 2."""

    @fuzz(40, budget)
    @given(
        st.one_of(
            config_docs.map(_toml_doc),
            st.text(max_size=200),
            st.binary(max_size=100).map(lambda b: b.decode("latin-1")),
        ),
        st.lists(
            st.one_of(
                st.tuples(schema_keys, toml_values).map(lambda x: f"{x[0][0]}.{x[0][1]}={_toml(x[1])}"),
                st.tuples(schema_keys, st.text(max_size=20)).map(lambda x: f"{x[0][0]}.{x[0][1]}={x[1]}"),
                st.text(max_size=30),
            ),
            max_size=3,
        ),
    )
    def prop(text, sets):
        p = tmp_path / "c.toml"
        p.write_text(text, encoding="utf-8", errors="surrogateescape")
        try:
            cfg = C.load(p)
        except C.ConfigError:
            cfg = None
        if cfg is not None:
            _assert_valid(cfg)
            try:
                _assert_valid(C.apply_overrides(cfg, sets))
            except C.ConfigError:
                pass
        argv = ["--config", str(p)] + [x for s in sets for x in ("--set", s)] + ["config"]
        rc, out, err = cli(argv, limit_s=20)
        assert rc in (0, 2)
        if rc == 0:
            import tomllib

            _assert_valid(C.validate(tomllib.loads(out), "<printed>"))  # what `config` prints loads again

    prop()


# a valid value for every key the pipeline reads (outputs, sources and GL back end are fuzzed elsewhere)
_RUN_SKIP = {("source", "url"), ("source", "calibration"), ("source", "response_curve"), ("model", "bundle"),
             ("render", "gl_backend"), ("imu", "url"), ("logging", "level")}  # fmt: skip
_RUN_KEYS = [(s, k) for s, keys in C.SCHEMA.items() if s not in ("output",) for k in keys if (s, k) not in _RUN_SKIP]


@st.composite
def valid_value(draw, section: str, key: str):
    f = C.SCHEMA[section][key]
    if f.choices is not None:
        return draw(st.sampled_from(f.choices))
    t = f.types[0]
    if t is bool:
        return draw(st.booleans())
    lo = f.gt if f.gt is not None else f.min
    hi = f.max
    if t is int:
        lo = int(lo) + (1 if f.gt is not None else 0) if lo is not None else -(2**31)
        return draw(st.integers(lo, int(hi) if hi is not None else lo + 10**6))
    if t is float:
        lo = float(lo) if lo is not None else -1e6
        v = draw(st.floats(lo, float(hi) if hi is not None else lo + 1e6, allow_nan=False))
        return v if f.gt is None or v > f.gt else f.gt + 1e-6
    if t is list and f.length is not None:
        if key == "rotation":
            return draw(st.sampled_from([[1.0, 0, 0, 0, 1, 0, 0, 0, 1], [0, -1, 0, 1, 0, 0, 0, 0, 1]]))
        return [draw(st.floats(f.min, f.max, allow_nan=False)) for _ in range(f.length)]
    return f.default


@pytest.mark.gl
@pytest.mark.parametrize("budget", BUDGETS)
def test_fuzz_valid_configuration_runs_or_says_why(tmp_path, gl, budget):
    """A configuration the schema accepts runs the pipeline (2 frames) or fails with one line; never a traceback."""

    @fuzz(2, budget)
    @given(st.data())
    def prop(data):
        keys = data.draw(st.lists(st.sampled_from(_RUN_KEYS), min_size=1, max_size=8, unique=True))
        doc: dict[str, dict] = {}
        for s, k in keys:
            doc.setdefault(s, {})[k] = data.draw(valid_value(s, k))
        p = tmp_path / "run.toml"
        p.write_text(_toml_doc(doc))
        rc, out, err = cli(
            ["--config", str(p), "run", "synthetic://indoor?size=64x48&frames=2", "--max-frames", "2"], limit_s=120
        )
        assert rc in (0, 1), (doc, err)

    prop()


# ------------------------------------------------------------------------------- source URLs

_KEYS = {
    "synthetic": ["seed", "size", "width", "height", "frames", "path", "hdr", "table", "lights", "bounce", "boxes"],
    "oakd": ["fps", "size", "mono", "queue", "imu", "imu_rate", "preset", "lr_check", "subpixel", "extended",
             "undistort", "exposure_us", "iso", "sync_ms", "timeout_s", "reconnect", "protocol"],
    "v4l2": ["stereo", "right", "size", "fps", "fourcc", "swap", "calib", "exposure_us", "scale", "reconnect"],
    "replay": ["timing", "loop", "max_frames"],
}  # fmt: skip
query_values = st.one_of(
    st.text(max_size=12),
    st.integers(-(2**40), 2**40).map(str),
    st.sampled_from(["0", "1", "-1", "nan", "inf", "1e309", "4096x4096", "0x0", "64x48", "32x32", "sbs", "usb",
                     "orbit", "99999999999999999999", "1.5", "", "%00", "a&b=c"]),
)  # fmt: skip


@st.composite
def source_urls(draw):
    scheme = draw(st.sampled_from(list(_KEYS) + ["", "file", "http"]) | st.text(max_size=6))
    keys = _KEYS.get(scheme, [])
    rest = draw(
        st.sampled_from(["indoor", "outdoor", "lamp", "cluttered", "spatial", "/dev/null", "192.168.1.44", ""])
        | st.text(max_size=15)
    )
    params = draw(st.lists(st.tuples(st.sampled_from(keys) if keys else st.text(max_size=6), query_values), max_size=4))
    query = "&".join(f"{k}={v}" for k, v in params)
    return f"{scheme}://{rest}" + (f"?{query}" if query else "")


@pytest.mark.parametrize("budget", BUDGETS)
def test_fuzz_source_urls(budget):
    """Any source URL: a Source or one IllumiNetError, quickly; small synthetic scenes also give a frame."""
    from illuminet.hw import open_source
    from illuminet.hw.synthetic.source import SyntheticSource

    @fuzz(40, budget)
    @given(source_urls())
    @example("synthetic://lamp?size=64x48&frames=3&boxes=1")  # a scene that builds and gives a frame
    def prop(url):
        t0 = time.monotonic()
        try:
            src = open_source(url)  # never opens a device: only parses and (synthetic) builds the scene
        except IllumiNetError as e:
            assert e.one_line() and "\n" not in e.one_line()
            assert time.monotonic() - t0 < 30
            return
        assert time.monotonic() - t0 < 30, f"{url}: construction took {time.monotonic() - t0:.1f} s"
        if isinstance(src, SyntheticSource) and src.scene.intrinsics.width * src.scene.intrinsics.height <= 128 * 128:
            with src:
                f = src.read()
            assert f is not None and np.isfinite(f.depth).all()

    prop()


@pytest.mark.parametrize("budget", BUDGETS)
def test_fuzz_source_urls_on_the_command_line(budget):
    """The same URLs through ``illuminet run`` refused before anything runs: one line, exit status 1 or 2."""

    @fuzz(10, budget)
    @given(source_urls().filter(lambda u: not u.startswith(("synthetic://", "oakd://")) or "?" in u))
    def prop(url):
        # --max-frames 1 and no outputs: a URL that is valid runs one frame (synthetic) or fails to
        # open a device (oakd/v4l2 are refused before any search when the URL is invalid)
        if url.startswith("oakd://"):
            from illuminet.hw.oakd import parse_url

            try:
                parse_url(url)
                return  # a valid oakd:// URL would search for devices (the network, unless usb)
            except ValueError:
                pass
        if url.startswith("synthetic://"):
            return  # building scenes is covered above
        cli(["run", url, "--max-frames", "1"], limit_s=60)

    prop()


# ------------------------------------------------------------------------------- serial IMU

imu_fields = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-(2**70), 2**70).map(str),
    st.sampled_from(["", "1e308", "-1e308", "nan", "inf", "9.81", "1_0", " 1", "0x10", "1e99999"]),
    st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=126), max_size=8),
)


@st.composite
def imu_lines(draw):
    """A line with a valid checksum and fields of any kind, or raw bytes."""
    if draw(st.booleans()):
        return draw(st.binary(max_size=300))
    talker = draw(st.sampled_from(["IMU", "GGA", ""]))
    fields = draw(st.lists(imu_fields, min_size=0, max_size=9))
    payload = ",".join([talker, *fields]).encode("ascii", "replace")
    cs = 0
    for b in payload:
        cs ^= b
    end = draw(st.sampled_from([b"\r\n", b"\n", b""]))
    return b"$" + payload + b"*" + f"{cs:02X}".encode() + end


@pytest.mark.parametrize("budget", BUDGETS)
def test_fuzz_serial_imu_line_parser(budget):
    """Any byte stream: never raises; only plausible samples come out; split reads parse the same."""
    from illuminet.hw.serial_imu import MAX_ACCEL, MAX_GYRO, ImuMatcher, LineParser, SerialImu

    @fuzz(100, budget)
    @given(st.lists(imu_lines(), max_size=12), st.lists(st.integers(1, 50), min_size=1, max_size=10))
    def prop(lines, cuts):
        stream = b"".join(lines)
        whole = LineParser().feed(stream)
        p = LineParser()
        pieces, i = [], 0
        for k in range(len(stream)):
            c = cuts[k % len(cuts)]
            if i >= len(stream):
                break
            pieces += p.feed(stream[i : i + c])
            i += c
        assert pieces == whole and p.good == len(whole)
        for s in whole:
            assert 0 <= s.t_ns <= 2**63 - 1
            assert all(math.isfinite(v) and abs(v) <= MAX_ACCEL for v in s.accel)
            assert s.gyro is None or all(math.isfinite(v) and abs(v) <= MAX_GYRO for v in s.gyro)
        # and through the reader's timestamp gate and the matcher: gravity is a unit vector or None
        imu = SerialImu("loop://", matcher=ImuMatcher(max_skew_ms=50.0), clock="device")
        for k, s in enumerate(whole):
            imu._accept(s, 10**12 + k * 5_000_000)
        if whole:
            _, g = imu.matcher.match(imu.last_sample.t_ns if imu.last_sample else 0)
            assert g is None or abs(float(np.linalg.norm(g)) - 1) < 1e-4

    prop()


# ------------------------------------------------------------------------- bundles and relight


@pytest.fixture(scope="module")
def bundle_copy(tmp_path_factory) -> Path:
    from illuminet.runtime.assets.bundle import load_bundle

    d = tmp_path_factory.mktemp("fuzz-bundle") / "b"
    shutil.copytree(load_bundle("builtin:vase").path, d, ignore=shutil.ignore_patterns("work"))
    return d


def _json_paths(obj, prefix=()):
    yield prefix
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _json_paths(v, (*prefix, k))
    elif isinstance(obj, list):
        for k, v in enumerate(obj):
            yield from _json_paths(v, (*prefix, k))


@pytest.mark.parametrize("budget", BUDGETS)
def test_fuzz_bundle_json(bundle_copy, budget):
    """Any bundle.json: a Bundle or one BundleError naming what is wrong; never another exception."""
    from illuminet.runtime.assets.bundle import BundleError, load_bundle

    original = json.loads((bundle_copy / "bundle.json").read_text())
    paths = [p for p in _json_paths(original) if p]

    @fuzz(40, budget)
    @given(
        st.lists(st.tuples(st.sampled_from(paths), st.booleans(), json_values), min_size=1, max_size=4),
        st.booleans(),
    )
    def prop(edits, whole_garbage):
        meta = json.loads(json.dumps(original))
        for path, delete, value in edits:
            node = meta
            for k in path[:-1]:
                if (
                    isinstance(node, dict)
                    and k in node
                    or isinstance(node, list)
                    and isinstance(k, int)
                    and k < len(node)
                ):
                    node = node[k]
                else:
                    node = None
                    break
            if isinstance(node, dict) and delete:
                node.pop(path[-1], None)
            elif isinstance(node, dict) or (
                isinstance(node, list) and isinstance(path[-1], int) and path[-1] < len(node)
            ):
                node[path[-1]] = value
        text = json.dumps(edits[0][2]) if whole_garbage else json.dumps(meta)
        (bundle_copy / "bundle.json").write_text(text)
        try:
            load_bundle(bundle_copy)
        except BundleError as e:
            assert "\n" not in e.one_line()
        finally:
            (bundle_copy / "bundle.json").write_text(json.dumps(original))

    prop()


image_specs = st.one_of(
    st.tuples(st.just("png8"), st.integers(1, 96), st.integers(1, 96), st.sampled_from([1, 3, 4])),
    st.tuples(st.just("png16"), st.integers(1, 96), st.integers(1, 96), st.sampled_from([1, 3])),
    st.tuples(st.just("npy"), st.lists(st.integers(0, 70), max_size=3), st.sampled_from(["f4", "f8", "u2", "i8", "O"])),
    st.tuples(st.just("npy_special"), st.sampled_from([np.nan, np.inf, -1.0, 0.0, 1e30])),
    st.tuples(st.just("header"), st.integers(0, 2**31 - 1), st.integers(0, 2**31 - 1)),
    st.tuples(st.just("bytes"), st.binary(max_size=64)),
    st.sampled_from([("missing",), ("dir",), ("npz",)]),
)


def _write_image(path: Path, spec) -> Path:
    import cv2

    kind = spec[0]
    rng = np.random.default_rng(0)
    if kind in ("png8", "png16"):
        dtype = np.uint8 if kind == "png8" else np.uint16
        shape = (spec[2], spec[1]) if spec[3] == 1 else (spec[2], spec[1], spec[3])
        img = rng.integers(0, np.iinfo(dtype).max, shape, dtype=dtype)
        path = path.with_suffix(".png")
        cv2.imwrite(str(path), img)
    elif kind == "npy":
        path = path.with_suffix(".npy")
        if spec[2] == "O":
            np.save(path, np.array([{"a": 1}], dtype=object), allow_pickle=True)
        else:
            np.save(path, rng.random(tuple(spec[1])).astype(spec[2]))
    elif kind == "npy_special":
        path = path.with_suffix(".npy")
        np.save(path, np.full((48, 64), spec[1], np.float32))
    elif kind == "header":
        path = path.with_suffix(".png")
        path.write_bytes(_png_header(spec[1], spec[2]) + b"\0" * 64)
    elif kind == "bytes":
        path = path.with_suffix(".png")
        path.write_bytes(spec[1])
    elif kind == "dir":
        path.mkdir()
    elif kind == "npz":
        path = path.with_suffix(".npy")
        with open(path, "wb") as f:
            np.savez(f, depth=np.ones((48, 64), np.float32))
    return path


@pytest.mark.parametrize("budget", BUDGETS)
def test_fuzz_relight_inputs(tmp_path, budget):
    """Any relight inputs: the npz (finite values) or one line with exit status 1 or 2, in bounded time."""
    import cv2

    good_c = tmp_path / "good_c.png"
    good_d = tmp_path / "good_d.png"
    cv2.imwrite(str(good_c), np.full((48, 64, 3), 128, np.uint8))
    cv2.imwrite(str(good_d), np.full((48, 64), 1500, np.uint16))
    counter = iter(range(10**9))

    @fuzz(8, budget)
    @given(
        st.one_of(st.just(None), image_specs),
        st.one_of(st.just(None), image_specs),
        st.one_of(
            st.just("50,50,32,24"),
            st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=0, max_size=5).map(
                lambda v: ",".join(map(repr, v))
            ),
            st.text(max_size=12),
        ),
        st.one_of(st.just("32,40"), st.tuples(st.integers(-(2**40), 2**40), st.integers(-10, 10**6)).map(
            lambda v: f"{v[0]},{v[1]}"), st.text(max_size=8)),
        st.sampled_from(["ok", "missing_dir", "is_dir"]),
    )  # fmt: skip
    @example(None, None, "50,50,32,24", "32,40", "ok")  # the valid inputs: a relit object every run
    def prop(color, depth, intr, anchor, out):
        k = next(counter)
        c = good_c if color is None else _write_image(tmp_path / f"c{k}", color)
        d = good_d if depth is None else _write_image(tmp_path / f"d{k}", depth)
        o = {"ok": tmp_path / f"r{k}.npz", "missing_dir": tmp_path / "nope" / "r.npz", "is_dir": tmp_path}[out]
        # --flag=VALUE: a value starting with '-' is a value, not a flag
        argv = ["relight", f"--color={c}", f"--depth={d}", f"--out={o}", f"--intrinsics={intr}", f"--anchor={anchor}"]
        rc, _, err = cli(argv, limit_s=60)
        if rc == 0:  # the result is finite (primary_dir / primary_pos are NaN by design when there is no such light)
            with np.load(o) as z:
                for name in ("vertices", "normals", "radiance", "irradiance", "proxy_irradiance", "T_cam_obj"):
                    assert np.isfinite(z[name]).all(), name

    prop()


# --------------------------------------------------------------------------------- HTTP server

http_paths = st.one_of(
    st.sampled_from(["/", "/index.html", "/viewer", "/stats.json", "/estimate.json", "/estimates", "/stream.mjpg",
                     "/stream.mjpg?source=camera", "/stream.mjpg?source=x", "/model.glb", "/light_estimate.schema.json",
                     "/static/viewer.js", "/static/../../etc/passwd", "/static/%2e%2e/%2e%2e/etc/passwd",
                     "/static/./index.html", "/static/.hidden", "//etc/passwd", "/static/three/../../../x", "*",
                     "http://evil.example/stats.json", "/" + "a" * 5000]),
    st.text(max_size=40).map(lambda t: "/" + t),
    st.text(max_size=40),
)  # fmt: skip
http_hosts = st.one_of(
    st.sampled_from(["127.0.0.1", "localhost", "[::1]", "evil.example", "", "a:b:c", "127.0.0.1:0"]),
    st.text(max_size=20),
)
header_lines = st.tuples(
    st.sampled_from(["Host", "Content-Length", "Connection", "Transfer-Encoding", "Range", "Accept"])
    | st.text(max_size=10),
    st.text(max_size=30) | st.integers(-5, 10**12).map(str),
)


@st.composite
def http_requests(draw) -> bytes:
    if draw(st.integers(0, 9)) == 0:
        return draw(st.binary(max_size=200))
    method = draw(st.sampled_from(["GET", "HEAD", "POST", "PUT", "DELETE", "OPTIONS", "CONNECT"]) | st.text(max_size=6))
    version = draw(st.sampled_from(["HTTP/1.1", "HTTP/1.0", "HTTP/2.0", "HTTP/0.9", ""]) | st.text(max_size=8))
    head = f"{method} {draw(http_paths)} {version}\r\n"
    if draw(st.booleans()):
        head += f"Host: {draw(http_hosts)}\r\n"
    for k, v in draw(st.lists(header_lines, max_size=4)):
        head += f"{k}: {v}\r\n"
    body = draw(st.binary(max_size=40))
    return head.encode("utf-8", "replace") + b"\r\n" + body


def _exchange(port: int, raw: bytes, limit: float = 1.0) -> bytes:
    """Send ``raw``, then read whatever comes for up to ``limit`` seconds (streams never end by themselves;
    an incomplete request gets no answer while the server waits for the rest of it)."""
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.settimeout(0.25)
        try:
            s.sendall(raw)
        except OSError:
            return b""
        data = b""
        t_end = time.monotonic() + limit
        while time.monotonic() < t_end and len(data) < 1 << 20:
            try:
                chunk = s.recv(65536)
            except TimeoutError:
                if data:
                    break  # an answer came and the connection idles (keep-alive or a stream between frames)
                continue
            except OSError:
                break
            if not chunk:
                break
            data += chunk
        return data


@pytest.mark.parametrize("budget", BUDGETS)
def test_fuzz_http_requests(capfd, budget):
    """Any request: answered or closed in bounded time; the server keeps serving; nothing outside its pages."""
    from illuminet.runtime.frame import Frame, Intrinsics
    from illuminet.runtime.stream import viewer
    from illuminet.runtime.stream.mjpeg import MjpegSink

    passwd = Path("/etc/passwd").read_bytes()[:40] if Path("/etc/passwd").is_file() else b"root:x:0:0"
    with MjpegSink(port=0, max_clients=8, client_timeout_s=2.0) as sink:
        stop = threading.Event()

        def feed():
            img = np.full((48, 64, 3), 90, np.uint8)
            intr = Intrinsics(50, 50, 32, 24, 64, 48)
            i = 0
            while not stop.is_set():
                sink.write(Frame(seq=i, t_device_ns=i, t_host_ns=i, color=img, depth=None, intrinsics=intr))
                i += 1
                time.sleep(0.02)

        feeder = threading.Thread(target=feed, daemon=True)
        feeder.start()
        try:

            @fuzz(30, budget)
            @given(http_requests())
            def prop(raw):
                t0 = time.monotonic()
                data = _exchange(sink.port, raw)
                assert time.monotonic() - t0 < 6
                assert passwd not in data
                if data.startswith(b"HTTP/1.") and b" 200 " in data.split(b"\r\n", 1)[0]:
                    line = raw.split(b"\r\n", 1)[0].split(b" ")
                    path = line[1].decode("utf-8", "replace") if len(line) > 1 else ""
                    if path.startswith("/static/"):  # a 200 for a static path is one of the pages' files
                        assert viewer.static_file(path[len("/static/") :].partition("?")[0]) is not None
                # the server still answers a plain request
                ok = _exchange(
                    sink.port, b"GET /stats.json HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n", 3.0
                )
                assert ok.startswith(b"HTTP/1.1 200"), ok[:100]

            prop()
        finally:
            stop.set()
            feeder.join(2)
        deadline = time.monotonic() + 10
        while sink.connections and time.monotonic() < deadline:  # every client thread ended
            time.sleep(0.05)
        assert sink.connections == 0
    err = capfd.readouterr().err
    assert "Traceback" not in err and "Exception occurred" not in err, err[-2000:]


@pytest.mark.parametrize("budget", BUDGETS)
def test_fuzz_static_paths_never_leave_the_package(budget):
    from illuminet.runtime.stream import viewer

    root = viewer.STATIC_DIR.resolve()

    @fuzz(200, budget)
    @given(
        st.lists(st.sampled_from(["..", ".", "", "three", "addons", "index.html", "%2e%2e", "\\", "\x00", "/"])
                 | st.text(max_size=6), max_size=6).map("/".join)
    )  # fmt: skip
    def prop(rel):
        got = viewer.static_file(rel)
        if got is not None:
            assert (root / rel).resolve().is_relative_to(root)

    prop()


def test_profiles_are_registered():
    """tests/conftest.py registers the fuzz profiles; the default one has no deadline."""
    assert settings.default.deadline is None
    assert settings.get_profile("illuminet").deadline is None
    assert settings.get_profile("illuminet-slow").max_examples > settings.get_profile("illuminet").max_examples
