"""The run / replay / record commands end to end, through the real CLI entry point."""

from __future__ import annotations

import json
import os
import signal

import cv2
import numpy as np
import pytest

from illuminet.cli import build_parser, main
from illuminet.commands.run import config_with_flags
from illuminet.pipeline import build_stages
from illuminet.runtime.config import defaults
from illuminet.runtime.stream.session import SessionReader

from ._sessions import cli, make_session, same_frame, spawn, wait_for_lines


@pytest.mark.parametrize(
    "cmd, flags",
    [
        (
            "run",
            [
                "--timing",
                "--loop",
                "--max-frames",
                "--video",
                "--png-dir",
                "--record",
                "--mjpeg",
                "--listen",
                "--port",
                "--strict",
                "--stats-json",
            ],
        ),
        (
            "replay",
            ["--check", "--timing", "--loop", "--max-frames", "--video", "--png-dir", "--record", "--stats-json"],
        ),
        ("record", ["SOURCE_URL", "OUT", "--color", "--jpeg-quality", "--no-fsync", "--max-frames", "--timing"]),
    ],
)
def test_help(capsys, cmd, flags):
    with pytest.raises(SystemExit) as e:
        main([cmd, "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    for f in flags:
        assert f in out, f"{cmd} --help does not mention {f}"


@pytest.mark.parametrize(
    "argv, says",
    [
        (
            ["demo", "--fames", "3"],
            "illuminet demo: error: unrecognized arguments: --fames 3 (--fames: did you mean --frames?)",
        ),
        (
            ["run", "--vido", "x.mp4"],
            "illuminet run: error: unrecognized arguments: --vido (--vido: did you mean --video?)",
        ),
        (
            ["calibrate", "board", "--sqares", "9x6"],
            "illuminet calibrate board: error: unrecognized arguments: --sqares",
        ),
        (["demo", "extra"], "illuminet demo: error: unrecognized arguments: extra; `illuminet demo --help` lists"),
    ],
)
def test_an_unknown_option_of_a_command_is_that_commands_error_with_the_close_option(capsys, argv, says):
    """`illuminet demo --fames 3` printed the top-level usage (`illuminet [-h] ... COMMAND ...`, none of
    demo's options) and 'illuminet: error: unrecognized arguments: --fames 3'."""
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2 and says in err, err
    assert f"usage: illuminet {argv[0]}" in err, err


def test_flags_override_the_config():
    args = build_parser().parse_args(
        [
            "run",
            "replay://x",
            "--timing",
            "asap",
            "--no-loop",
            "--max-frames",
            "5",
            "--png-dir",
            "p",
            "--port",
            "9000",
            "--strict",
            "--stats-json",
            "s.json",
        ]
    )
    cfg = config_with_flags(args, defaults())
    assert cfg.source.timing == "asap" and cfg.source.loop is False and cfg.source.max_frames == 5
    assert cfg.output.png_dir == "p" and cfg.output.port == 9000 and cfg.output.video == ""
    assert cfg.logging.strict is True and cfg.logging.stats_json == "s.json"
    args = build_parser().parse_args(["run"])
    assert config_with_flags(args, defaults()).to_dict() == defaults().to_dict()


def test_record_then_replay_end_to_end(tmp_path, capsys):
    src = make_session(tmp_path / "src", 9)
    rec = tmp_path / "rec"
    rc = main(
        [
            "record",
            f"replay://{tmp_path}/src?timing=asap",
            str(rec),
            "--no-fsync",
            "--stats-json",
            str(tmp_path / "rec.json"),
        ]
    )
    assert rc == 0
    out = capsys.readouterr().out
    assert "sink:record" in out and "9 frames in" in out
    r = SessionReader(rec, strict=True)
    assert r.finalized and len(r) == 9 and r.manifest["source"].startswith("replay://")
    for a, b in zip(src, r):
        assert same_frame(a, b)
    st = json.loads((tmp_path / "rec.json").read_text())
    assert st["frames"] == 9 and "sink:record" in st["steps"]

    p = cli(
        "replay",
        str(rec),
        "--timing",
        "asap",
        "--png-dir",
        str(tmp_path / "png"),
        "--video",
        str(tmp_path / "out.avi"),
        "--stats-json",
        str(tmp_path / "replay.json"),
    )
    assert p.returncode == 0, p.stderr
    pngs = sorted((tmp_path / "png").glob("*.png"))
    assert [p.name for p in pngs] == [f"frame_{k:06d}.png" for k in range(9)]
    # the output is the input picture with the object composited where it stands (build_stages
    # runs the full chain): same size, and unchanged away from the object and its shadow
    png = cv2.imread(str(pngs[4]))[..., ::-1]
    assert png.shape == src[4].color.shape
    assert (png == src[4].color).all(axis=-1).mean() > 0.7
    st = json.loads((tmp_path / "replay.json").read_text())
    assert st["frames"] == 9 and st["dropped"] == 0 and st["end_reason"] == "end of stream"
    stages = [f"stage:{s.name}" for s in build_stages(defaults())]
    assert {"source", "sink:png", "sink:video", "total", *stages} <= set(st["steps"])
    assert (tmp_path / "out.avi").stat().st_size > 0

    rc = main(["replay", str(rec), "--check"])
    assert rc == 0 and "9 intact frames, finalised" in capsys.readouterr().out


def test_run_records_its_input_while_processing(tmp_path):
    src = make_session(tmp_path / "s", 6)
    p = cli("run", f"replay://{tmp_path}/s?timing=asap", "--record", str(tmp_path / "rec"), "--no-mjpeg")
    assert p.returncode == 0, p.stderr
    r = SessionReader(tmp_path / "rec", strict=True)
    assert len(r) == 6 and all(same_frame(a, b) for a, b in zip(src, r))


def test_run_with_loop_and_max_frames(tmp_path, capsys):
    make_session(tmp_path / "s", 4)
    p = cli(
        "run",
        f"replay://{tmp_path}/s",
        "--timing",
        "asap",
        "--loop",
        "--max-frames",
        "10",
        "--stats-json",
        str(tmp_path / "st.json"),
    )
    assert p.returncode == 0, p.stderr
    st = json.loads((tmp_path / "st.json").read_text())
    assert st["frames"] == 10


def test_record_from_synthetic(tmp_path):
    rc = main(
        [
            "record",
            "synthetic://indoor?seed=0",
            str(tmp_path / "rec"),
            "--max-frames",
            "3",
            "--timing",
            "asap",
            "--no-fsync",
        ]
    )
    assert rc == 0
    r = SessionReader(tmp_path / "rec", strict=True)
    assert len(r) == 3 and r.has_depth


def test_replay_check_lists_problems(tmp_path, capsys):
    make_session(tmp_path / "s", 5)
    (tmp_path / "s" / "frames" / "000002.depth.png").unlink()
    rc = main(["replay", str(tmp_path / "s"), "--check"])
    out = capsys.readouterr().out
    assert rc == 1 and "problem:" in out and "000002.depth.png" in out and "4 intact frames" in out


def test_replay_check_escapes_a_sessions_control_characters(tmp_path, capsys):
    """A manifest's source and an index's file names went to the terminal raw: an escape sequence
    in them could clear the screen or print a fake 'OK'."""
    s = tmp_path / "s"
    make_session(s, 3)
    m = json.loads((s / "manifest.json").read_text())
    m["source"] = "\x1b[2Jevil"
    (s / "manifest.json").write_text(json.dumps(m))
    lines = (s / "frames.jsonl").read_text().splitlines()
    d = json.loads(lines[1])
    d["color"] = "frames/\x1b[1A\rOK.png"
    lines[1] = json.dumps(d)
    (s / "frames.jsonl").write_text("\n".join(lines) + "\n")
    rc = main(["replay", str(s), "--check"])
    out = capsys.readouterr().out
    assert rc == 1 and "\x1b" not in out and "\r" not in out, out
    assert "source \\x1b[2Jevil" in out and "missing file" in out and "\\x1b[1A\\rOK.png" in out, out


def test_replay_check_of_a_session_without_frames_is_not_ok(tmp_path, capsys):
    s = tmp_path / "s"
    make_session(s, 2)
    (s / "frames.jsonl").write_text("")
    rc = main(["replay", str(s), "--check"])
    out = capsys.readouterr().out
    assert rc == 1 and "problem: no intact frame: nothing to replay" in out and "OK" not in out.splitlines()


def test_replay_of_a_damaged_session_plays_the_intact_part(tmp_path, capsys):
    make_session(tmp_path / "s", 5)
    (tmp_path / "s" / "frames" / "000002.depth.png").unlink()
    p = cli("replay", str(tmp_path / "s"), "--timing", "asap")
    assert p.returncode == 0 and "4 frames in" in p.stdout, p.stderr
    assert "000002.depth.png" in p.stderr  # the warning names the damage
    rc = main(["replay", str(tmp_path / "s"), "--timing", "asap", "--strict"])
    assert rc == 1 and "invalid session" in capsys.readouterr().err


@pytest.mark.parametrize(
    "flag, says",
    [("--estimates", "an estimates file"), ("--stats-json", "a statistics file"), ("--video", "a video file")],
)
def test_an_output_file_that_is_a_folder_is_refused_in_one_line(tmp_path, capsys, flag, says):
    """`--estimates out` (a folder) said 'expected a estimates file path'."""
    rc = main(["run", "synthetic://indoor?frames=2&size=64x48", flag, str(tmp_path)])
    err = capsys.readouterr().err
    assert rc == 2 and f"{tmp_path} is a folder; expected {says} path" in err, err


@pytest.mark.parametrize(
    "flag, name",
    [
        ("--estimates", "estimates.jsonl"),
        ("--stats-json", "manifest.json"),
        ("--video", "x.mp4"),
        ("--png-dir", "frames"),
        ("--record", "again"),
    ],
)
def test_replay_outputs_never_write_into_the_session_being_replayed(tmp_path, capsys, flag, name):
    """`replay S --estimates S/estimates.jsonl` replaced the recorded estimates, and `--stats-json
    S/manifest.json` the manifest (the session no longer opened). Refused before the run now."""
    s = tmp_path / "s"
    make_session(s, 2)
    before = {p.relative_to(s): p.read_bytes() for p in s.rglob("*") if p.is_file()}
    for cmd in (["replay", str(s)], ["run", f"replay://{s}"]):
        assert main([*cmd, "--timing", "asap", flag, str(s / name)]) == 2
        err = capsys.readouterr().err
        assert f"{s / name} is inside the session being replayed ({s})" in err, err
    assert {p.relative_to(s): p.read_bytes() for p in s.rglob("*") if p.is_file()} == before


@pytest.mark.parametrize(
    "flag, name",
    [("--estimates", "frames.jsonl"), ("--stats-json", "manifest.json"), ("--png-dir", "frames"), ("--video", "x.mp4")],
)
def test_outputs_never_write_into_another_recorded_session(tmp_path, capsys, flag, name):
    """Only the replayed session was protected: `run SRC --estimates OTHER/frames.jsonl` replaced another
    recording's index ("no intact frame" after), `--stats-json OTHER/manifest.json` its manifest, and
    `--png-dir OTHER/frames` added PNGs among its frames. The demo had no check at all."""
    s = tmp_path / "other"
    make_session(s, 2)
    before = {p.relative_to(s): p.read_bytes() for p in s.rglob("*") if p.is_file()}
    src = "synthetic://indoor?frames=2&size=64x48"
    for cmd in (["run", src, "--timing", "asap"], ["demo", "--source", src, "--frames", "2", "--no-video"]):
        if cmd[0] == "demo" and flag == "--video":
            cmd, flag_used = cmd[:-1], "--out"  # the demo's video flag
        else:
            flag_used = flag
        assert main([*cmd, flag_used, str(s / name)]) == 2
        err = capsys.readouterr().err
        assert f"{s / name} is inside the recorded session {s}; writing there would damage the recording" in err, err
        assert "Traceback" not in err
    assert {p.relative_to(s): p.read_bytes() for p in s.rglob("*") if p.is_file()} == before


@pytest.mark.parametrize("flag, name", [("--estimates", "frames.jsonl"), ("--stats-json", "manifest.json")])
def test_an_output_hard_linked_to_a_sessions_file_is_refused(tmp_path, capsys, flag, name):
    """A hard link outside the folder is the session's own file under another name: `replay S
    --stats-json LINK` replaced S's manifest with the statistics (the session no longer opened)."""
    s = tmp_path / "s"
    make_session(s, 2)
    before = {p.relative_to(s): p.read_bytes() for p in s.rglob("*") if p.is_file()}
    link = tmp_path / "link.json"
    os.link(s / name, link)
    assert main(["replay", str(s), "--timing", "asap", flag, str(link)]) == 2
    err = capsys.readouterr().err
    assert f"{link} has 2 hard links; writing it would also change the same file" in err, err
    assert {p.relative_to(s): p.read_bytes() for p in s.rglob("*") if p.is_file()} == before


def test_outputs_never_write_into_the_session_being_recorded(tmp_path, capsys):
    """`run SRC --record R --estimates R/frames.jsonl` gave rc 0 and a session whose index had an
    estimate line in it (`--check`: "missing key 'i'"); the same with `--stats-json R/manifest.json`."""
    r = tmp_path / "r"
    src = "synthetic://indoor?frames=2&size=64x48"
    for flag, name in (("--estimates", "frames.jsonl"), ("--stats-json", "manifest.json")):
        assert main(["run", src, "--timing", "asap", "--record", str(r), flag, str(r / name)]) == 2
        err = capsys.readouterr().err
        assert f"{r / name} is inside the session this run records ({r})" in err, err
    assert not r.exists()  # refused before anything was written


def test_estimates_to_stdout_are_the_only_thing_on_stdout(capsys):
    """`--estimates -` is documented as stdout, but the run's report (timing table, statistics) and the
    demo's "demo: source" line went there too: a JSON reader downstream broke on the first of them."""
    src = "synthetic://lamp?frames=3&size=64x48"
    for cmd in (["run", src, "--timing", "asap"], ["demo", "--source", src, "--frames", "3", "--no-video"]):
        assert main([*cmd, "--estimates", "-"]) == 0
        out, err = capsys.readouterr()
        lines = out.splitlines()
        assert lines and all(json.loads(x)["schema"] == "illuminet-light-estimate" for x in lines), out[:300]
        assert "total" in err  # the report is still shown, on stderr


def test_a_response_curve_that_cannot_be_read_is_one_line(tmp_path, capsys):
    """[source] response_curve missing or not a table: a ValueError traceback from run and replay."""
    bad = tmp_path / "c.png"
    bad.write_text("hi")
    for value, says in ((tmp_path / "none.json", "response curve file not found"), (bad, "cannot read")):
        rc = main(["--set", f"source.response_curve={value}", "run", "synthetic://indoor?frames=2&size=64x48"])
        err = capsys.readouterr().err
        assert rc == 2 and f"[source] response_curve: {value}: " in err and says in err, err
        assert "Traceback" not in err


def test_replay_of_a_path_near_a_session_names_the_session(tmp_path, capsys):
    """`replay S/manifest.json`, `replay S/frames` and `replay FOLDER_OF_SESSIONS` said only 'not a
    folder' / 'manifest.json: missing; not a recorded session'; the session to give was right there."""
    s = tmp_path / "runs" / "s1"
    make_session(s, 2)
    make_session(tmp_path / "runs" / "s2", 2)
    for given in (s / "manifest.json", s / "frames"):
        assert main(["replay", str(given)]) == 1
        err = capsys.readouterr().err
        assert f"; the session is {s}: give that folder" in err, err
    assert main(["run", f"replay://{s / 'manifest.json'}"]) == 1
    assert f"; the session is {s}: give that folder" in capsys.readouterr().err
    assert main(["replay", str(tmp_path / "runs")]) == 1
    err = capsys.readouterr().err
    assert f"; it holds the session(s) s1, s2: give one of them, e.g. {s}" in err, err


def test_clear_errors(tmp_path, capsys):
    assert main(["replay", str(tmp_path / "nope")]) == 1
    assert "is not a folder" in capsys.readouterr().err
    assert main(["run", "webcam://0"]) == 2  # a malformed URL is a usage mistake
    assert "unknown source scheme 'webcam'" in capsys.readouterr().err
    assert main(["--set", "output.port=80.5", "run", "replay://x"]) == 2
    assert "[output] port: expected int" in capsys.readouterr().err
    make_session(tmp_path / "s", 2)
    make_session(tmp_path / "exists", 2)
    assert main(["record", f"replay://{tmp_path}/s?timing=asap", str(tmp_path / "exists")]) == 1
    assert "already contains a session" in capsys.readouterr().err
    assert main(["run", f"replay://{tmp_path}/s", "--video", str(tmp_path / "v.gif")]) == 1
    assert "unknown extension '.gif'" in capsys.readouterr().err


def test_cli_record_killed_with_sigkill_replays_complete_frames(tmp_path):
    """kill -9 of the real `illuminet record` process: the session replays every complete frame."""
    make_session(tmp_path / "src", 10, fps=120.0)
    out = tmp_path / "rec"
    proc = spawn(["-m", "illuminet", "record", f"replay://{tmp_path}/src?timing=recorded&loop=1", str(out)])
    try:
        wait_for_lines(out / "frames.jsonl", 10, proc)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
    n = (out / "frames.jsonl").read_bytes().count(b"\n")
    r = SessionReader(out)
    assert not r.finalized and len(r) == n >= 10
    src = list(SessionReader(tmp_path / "src"))
    for f in r:
        assert np.array_equal(f.color, src[f.seq % 10].color) and np.array_equal(f.depth, src[f.seq % 10].depth)
    p = cli("replay", str(out), "--timing", "asap", "--stats-json", str(tmp_path / "st.json"))
    assert p.returncode == 0, p.stderr
    assert json.loads((tmp_path / "st.json").read_text())["frames"] == n


def test_bench_replay_reports_its_figures(capsys):
    from illuminet.bench.replay import measure

    d = measure(12, 2, defaults(), width=64, height=48, colors=("png", "raw"))  # the real path, small frames
    out = capsys.readouterr().out
    assert "median" in out and "frames/s" in out and "CPU time" in out and "source" in out
    assert d["frames"] == 12 and (d["width"], d["height"]) == (64, 48)
    assert len(d["replay_fps_runs"]) == 2 and d["replay_fps_median"] > 0 and d["cpu_ms_per_frame"] > 0
    assert d["steps"]["source"]["n"] == 13  # 12 frames + the end-of-stream read
    assert set(d["by_color"]) == {"png", "raw"} and d["by_color"]["raw"]["bytes_per_frame"] > 64 * 48 * 3
    json.dumps(d)


def test_bench_command_lists_replay(capsys):
    with pytest.raises(SystemExit):
        main(["bench", "--help"])
    assert "replay" in capsys.readouterr().out


def test_bench_help_describes_replay_by_what_it_measures():
    """`illuminet bench --help` said replay measured "MJPEG clients' cost", which the replay benchmark
    never did (that is the mjpeg benchmark's): a user picked the wrong one."""
    from illuminet.commands.bench import BENCHES

    assert "mjpeg" not in BENCHES["replay"].lower()
    assert "mjpeg" in BENCHES["mjpeg"].lower()


def test_global_options_are_also_taken_after_the_command(tmp_path, capsys):
    # where people type them: `illuminet demo --set a.b=1`; both places count, the later file wins
    cfg = tmp_path / "c.toml"
    cfg.write_text("[light]\nrate_hz = 7.0\n")
    assert main(["--set", "light.rate_hz=4", "config", "--set", "light.time_constant_s=0.3"]) == 0
    out = capsys.readouterr().out
    assert "rate_hz = 4.0" in out and "time_constant_s = 0.3" in out
    assert main(["config", "-c", str(cfg), "--set", "light.search_every=3"]) == 0
    out = capsys.readouterr().out
    assert "rate_hz = 7.0" in out and "search_every = 3" in out
    assert main(["config", "--set", "light.rate_hz=abc"]) == 2
    assert "[light] rate_hz" in capsys.readouterr().err


def test_a_flag_value_starting_with_a_dash_gets_the_fix(capsys):
    """``--exposure -5,100``: argparse takes ``-5,100`` for a flag and said only "expected one argument"."""
    with pytest.raises(SystemExit) as e:
        main(["relight", "--exposure", "-5,100"])
    assert e.value.code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert "argument --exposure: expected one argument" in last and "--exposure=-5,100" in last, last


def test_demo_with_an_unknown_built_in_object_says_one_thing(capsys):
    """`demo --set model.bundle="builtin:teapot"` printed "the SH baseline drives the shading", then
    failed on the unknown object: two lines that contradict each other."""
    rc = main(["demo", "--set", 'model.bundle="builtin:teapot"', "--frames", "2", "--no-video"])
    out, err = capsys.readouterr()
    assert rc == 2 and "SH baseline" not in out + err  # a configuration mistake (the bundle key)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "unknown built-in object 'teapot'" in lines[0], lines


def test_a_run_without_any_output_says_so(tmp_path, capsys):
    """`illuminet run SOURCE` alone processed 60 frames and wrote nothing, with no hint why."""
    src = "synthetic://indoor?frames=2&size=64x48"
    assert main(["run", src, "--timing", "asap"]) == 0
    assert "no output was given, so the frames were processed and dropped" in capsys.readouterr().err
    assert main(["run", src, "--timing", "asap", "--estimates", str(tmp_path / "e.jsonl")]) == 0
    assert "no output was given" not in capsys.readouterr().err
    # a live source (a camera) runs until Ctrl-C: the note comes at the start, once, not after the run
    assert main(["run", "synthetic://indoor?live=1&fps=60&frames=3&size=64x48"]) == 0
    err = capsys.readouterr().err
    assert "note: no output is given, so the frames are processed and dropped; add --video" in err, err
    assert err.count("processed and dropped") == 1, err


def test_server_flags_without_mjpeg_get_a_note(tmp_path, capsys):
    """`--viewer-model` (even a missing file), `--listen` and `--port` without `--mjpeg` were silently unused."""
    src = "synthetic://indoor?frames=2&size=64x48"
    out = ["--estimates", str(tmp_path / "e.jsonl")]
    assert main(["run", src, "--timing", "asap", *out, "--viewer-model", str(tmp_path / "no.glb")]) == 0
    assert "note: --viewer-model applies to the --mjpeg server only" in capsys.readouterr().err
    assert main(["demo", "--source", src, "--frames", "2", "--no-video", "--port", "9999"]) == 0
    assert "note: --port applies to the --mjpeg server only" in capsys.readouterr().err
    assert main(["run", src, "--timing", "asap", *out]) == 0
    assert "note:" not in capsys.readouterr().err


def test_an_output_that_fails_its_frames_makes_the_run_exit_1(tmp_path, capsys, monkeypatch):
    """A PNG folder on a full disk failed every frame (40 sink failures) and the run exited 0; the
    stream still goes on to the end (a live stream survives a bad frame), then says so and exits 1."""
    if not os.path.exists("/dev/full"):
        pytest.skip("needs /dev/full (a device that is always full)")
    png = tmp_path / "png"
    png.mkdir()
    for k in range(3):  # every frame's file is written to a device that is always full: ENOSPC
        os.symlink("/dev/full", png / f"frame_{k:06d}.png")
    src = "synthetic://indoor?frames=3&size=64x48"
    rc = main(["run", src, "--timing", "asap", "--png-dir", str(png)])
    out, err = capsys.readouterr()
    assert rc == 1 and "3 frame(s) missing from an output" in err, err
    assert "3 frames in" in out  # every frame was still processed


def test_the_run_report_lists_each_stages_counters(tmp_path, capsys):
    """docs/runtime.md sends users to "the imu stage's counters in the run's statistics" for skipped IMU
    lines, but `run` printed only the timing table and the source's counters."""
    src = "synthetic://indoor?frames=2&size=64x48"
    argv = ["run", src, "--timing", "asap", "--estimates", str(tmp_path / "e.jsonl"), "--set", 'imu.url="loop://"']
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "  imu: good=" in out and "implausible=" in out and "  planes: frames=2" in out, out[-600:]


def test_stats_json_dash_is_standard_output_and_the_report_moves_to_stderr(tmp_path, capsys):
    """--stats-json - wrote a file named '-'; it is stdout (as --estimates - is), the report on stderr;
    both on stdout at once is refused."""
    make_session(tmp_path / "src", 4)
    url = f"replay://{tmp_path}/src?timing=asap"
    assert main(["run", url, "--stats-json", "-"]) == 0
    cap = capsys.readouterr()
    assert json.loads(cap.out)["frames"] == 4 and "step" in cap.err
    assert not (tmp_path / "-").exists()
    assert main(["run", url, "--stats-json", "-", "--estimates", "-"]) == 2
    assert "[logging] stats_json: - (standard output) is where --estimates - writes" in capsys.readouterr().err


def test_ctrl_c_swallowed_during_start_up_still_stops_the_run(monkeypatch, capsys):
    """trimesh wraps its optional imports in ``except BaseException``: a Ctrl-C that landed there while
    the outputs were being built raised KeyboardInterrupt into that handler and was lost, and the run
    went on to its end (on a camera: until a second Ctrl-C). The CLI remembers it and the loop stops."""
    import illuminet.pipeline

    build_sinks = illuminet.pipeline.build_sinks

    def swallowing(*a, **k):
        try:  # what a library that catches BaseException does with a Ctrl-C during its import
            signal.raise_signal(signal.SIGINT)
        except BaseException:
            pass
        return build_sinks(*a, **k)

    monkeypatch.setattr(illuminet.pipeline, "build_sinks", swallowing)
    before = signal.getsignal(signal.SIGINT)
    try:
        rc = main(["run", "synthetic://indoor?frames=40&size=64x48"])
    finally:
        signal.signal(signal.SIGINT, before)
    out = capsys.readouterr().out
    assert rc == 0
    assert "0 frames in" in out and "ended: stopped" in out


@pytest.mark.parametrize("cmd", ["run", "demo"])
def test_signals_during_the_final_cleanup_keep_the_stats_json(tmp_path, cmd):
    """A second SIGTERM (or a Ctrl-C) while `run`/`demo` wrote their report after the loop killed the
    process with the default handler (or raised inside the write): no --stats-json file at all. The
    signals here arrive exactly then, sent by the process to itself from the report's first step."""
    import subprocess
    import sys

    from ._sessions import REPO, env

    out = tmp_path / "st.json"
    out.write_text("previous")
    if cmd == "run":
        argv = ["run", "synthetic://indoor?frames=2&size=64x48", "--timing", "asap", "--stats-json", str(out)]
    else:
        argv = ["demo", "--frames", "2", "--no-video", "--still", str(tmp_path / "s.png"), "--stats-json", str(out)]
    script = (
        "import os, signal, sys\n"
        "from illuminet.runtime.stream.loop import LoopStats\n"
        "from illuminet.cli import main\n"
        "orig = LoopStats.format_stats\n"
        "def format_stats(self, *a, **k):\n"
        "    for s in (signal.SIGTERM, signal.SIGTERM, signal.SIGINT):\n"
        "        os.kill(os.getpid(), s)\n"
        "    return orig(self, *a, **k)\n"
        "LoopStats.format_stats = format_stats\n"
        f"sys.exit(main({argv!r}))\n"
    )
    p = subprocess.run([sys.executable, "-c", script], cwd=REPO, env=env(), capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, (p.returncode, p.stderr[-2000:])
    assert json.loads(out.read_text())["frames"] == 2
    assert "Traceback" not in p.stderr
    assert not list(tmp_path.glob(".st.tmp-*"))
