"""Terminal progress: the live status line of run/replay/record (on a terminal only) and the tqdm bars
of train/eval."""

from __future__ import annotations

import io
import logging
import os
import pty
import subprocess
import sys

from illuminet.progress import StatusLine

from ._sessions import env, make_session

SNAP = {
    "frames": 12,
    "fps": 30.2,
    "fps_recent": 29.5,
    "dropped": 1,
    "failed_frames": 0,
    "sink_failures": 0,
    "elapsed_s": 0.4,
}


def test_status_line_draws_only_when_enabled_and_clears_for_log_records():
    quiet = io.StringIO()
    s = StatusLine(quiet)  # a StringIO is no terminal
    s.update(SNAP)
    s.close()
    assert quiet.getvalue() == ""

    out = io.StringIO()
    handler = logging.StreamHandler(out)
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        s = StatusLine(out, enabled=True)
        s.update(SNAP)
        assert out.getvalue() == "\rframes 12  29.5 fps  dropped 1  failed 0  0.4 s\x1b[K"
        logging.getLogger("illuminet.test").warning("something happened")
        # the status line is erased before the record, so the message starts on a clean line
        assert out.getvalue().endswith("\r\x1b[Ksomething happened\n")
        s.update(dict(SNAP, frames=13, sink_failures=2))
        assert "sink failures 2" in out.getvalue().rsplit("\r", 1)[1]
        s.close()
        assert out.getvalue().endswith("\r\x1b[K")
        s.close()  # idempotent
        n = len(out.getvalue())
        logging.getLogger("illuminet.test").warning("after")
        assert out.getvalue()[n:] == "after\n"  # the filter is gone with the line
    finally:
        root.removeHandler(handler)


def _run(args, tty: bool) -> str:
    """``python -m illuminet ARGS`` with stderr on a pseudo-terminal or a pipe; returns stderr."""
    if not tty:
        p = subprocess.run(
            [sys.executable, "-m", "illuminet", *args], env=env(), capture_output=True, text=True, timeout=120
        )
        assert p.returncode == 0, p.stderr
        return p.stderr
    master, slave = pty.openpty()
    p = subprocess.Popen(
        [sys.executable, "-m", "illuminet", *args],
        env=dict(env(), TERM="xterm"),
        stdout=subprocess.DEVNULL,
        stderr=slave,
    )
    os.close(slave)
    chunks = []
    while True:
        try:
            b = os.read(master, 65536)
        except OSError:  # EIO: the child closed the terminal
            break
        if not b:
            break
        chunks.append(b)
    os.close(master)
    assert p.wait(120) == 0
    return b"".join(chunks).decode(errors="replace")


def test_record_shows_the_status_line_on_a_terminal_and_nothing_when_piped(tmp_path):
    make_session(tmp_path / "s", 40, fps=40.0)
    url = f"replay://{tmp_path}/s"  # recorded timing: ~1 s, so the line is drawn a few times
    args = ["--log-level", "warning", "record", url, str(tmp_path / "r1"), "--no-fsync"]
    err = _run(args, tty=True)
    assert "\rframes " in err and " fps  dropped 0  failed 0" in err and "\x1b[K" in err
    args[4] = str(tmp_path / "r2")
    err = _run(args, tty=False)
    assert "\r" not in err and "fps  dropped" not in err


def test_training_progress_is_tqdm_and_quiet_when_not_a_terminal(capsys):
    from illuminet.models.train import Progress

    bar = Progress("stage", 10)
    for i in range(10):
        bar(i + 1, extra=f"loss {i}")
    assert bar._bar is None  # closed at the end
    assert capsys.readouterr().err == ""  # stderr is captured (no terminal): tqdm stays quiet

    import tqdm

    b = Progress("x", 5)
    b._bar = tqdm.tqdm(total=5, file=io.StringIO(), mininterval=0)  # as tqdm draws on a terminal
    out = b._bar.fp
    b(3, extra="loss 0.5")
    assert "3/5" in out.getvalue() and "loss 0.5" in out.getvalue()
    b(5)
    assert "5/5" in out.getvalue()


def test_a_job_progress_without_tqdm_prints_a_line_at_each_tenth_on_a_terminal(monkeypatch, capsys):
    """A plain install has no tqdm: eval and datagen showed nothing for a minute. On a terminal they
    now print a plain line at each tenth; piped, nothing (logs keep their own lines)."""
    import builtins
    import sys

    from illuminet.models.train import Progress

    real_import = builtins.__import__

    def no_tqdm(name, *a, **k):
        if name == "tqdm":
            raise ImportError("no tqdm")
        return real_import(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_tqdm)
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True, raising=False)
    bar = Progress("camera", 40)
    for i in range(1, 41):
        bar(i, extra="indoor")
    lines = capsys.readouterr().err.splitlines()
    assert lines[0] == "camera: 4/40 (indoor)" and lines[-1] == "camera: 40/40 (indoor)" and len(lines) == 10
    monkeypatch.setattr(sys.stderr, "isatty", lambda: False, raising=False)
    bar = Progress("camera", 40)
    bar(40)
    assert capsys.readouterr().err == ""
