"""``illuminet run SOURCE_URL``, ``illuminet replay SESSION``, ``illuminet record SOURCE_URL OUT``.

All three run the streaming loop (:func:`illuminet.runtime.stream.loop.run_loop`); they differ in the source
and the stages: ``run`` and ``replay`` process frames through the configured pipeline
(:func:`illuminet.pipeline.build_stages`), ``record`` only records the input. Command-line flags
override the configuration file (they are applied as ``--set`` overrides, so they are validated the
same way). On a terminal a live status line shows frames, fps, drops and failures
(:class:`illuminet.progress.StatusLine`; nothing when piped). At the end the per-step timing table
is printed; ``--stats-json`` writes it as JSON.

Exit codes: 0 done (also after Ctrl-C / SIGTERM, outputs finalised), 1 the source or an output failed,
2 configuration error.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from urllib.parse import quote

from illuminet.progress import StatusLine
from illuminet.runtime.config import Config, ConfigError, apply_overrides
from illuminet.runtime.errors import IllumiNetError, OutputPathError
from illuminet.runtime.stream.loop import LoopStats, loop_options, run_loop, signals_held
from illuminet.runtime.stream.session import SessionError, SessionReader, printable

log = logging.getLogger("illuminet.run")


def _add_source_flags(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("source (override [source])")
    g.add_argument(
        "--timing",
        choices=("recorded", "asap"),
        help="replay timing: follow recorded timestamps, or as fast as possible ([source] timing)",
    )
    g.add_argument(
        "--loop",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="replay: start again at the end ([source] loop)",
    )
    g.add_argument(
        "--max-frames", type=int, metavar="N", help="stop after N frames, 0 = no limit ([source] max_frames)"
    )


def add_live_output_flags(g) -> None:
    """--estimates, --mjpeg, --listen, --port, --viewer-model (shared with ``illuminet demo``)."""
    g.add_argument(
        "--estimates",
        metavar="FILE",
        help="write each frame's lighting estimate as a JSON line to FILE ('-' = stdout; docs/estimate.md)",
    )
    g.add_argument(
        "--mjpeg",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="serve the output over HTTP: the stream at /, a lit 3D viewer at /viewer, the "
        "estimate at /estimates (Server-Sent Events) and /estimate.json",
    )
    g.add_argument("--listen", metavar="ADDR", help="MJPEG bind address (default 127.0.0.1; 0.0.0.0 = local network)")
    g.add_argument("--port", type=int, help="MJPEG port ([output] port)")
    g.add_argument(
        "--viewer-model",
        metavar="PATH",
        help="model /viewer draws: .glb/.gltf/.obj/.ply/.stl or builtin:NAME ([output] viewer_model)",
    )


def _add_output_flags(p: argparse.ArgumentParser, *, record: bool = True) -> None:
    g = p.add_argument_group("outputs (override [output])")
    g.add_argument("--video", metavar="PATH", help="write the output to a video file (.mp4, .m4v, .mov, .mkv, .avi)")
    g.add_argument("--fps", type=float, help="frame rate written into the video file ([output] fps)")
    g.add_argument("--png-dir", metavar="DIR", help="write a PNG per output frame into DIR")
    if record:
        g.add_argument(
            "--record",
            metavar="DIR",
            help="also record the input frames (and their lighting estimates, estimates.jsonl) as a session in DIR",
        )
    add_live_output_flags(g)
    g = p.add_argument_group("run control (override [logging])")
    g.add_argument(
        "--strict",
        action="store_true",
        default=None,
        help="stop at the first failing frame with a traceback instead of counting it",
    )
    g.add_argument(
        "--stats-json", metavar="PATH", help="write the per-step timing statistics as JSON at the end (- = stdout)"
    )


def register(sub) -> None:
    p = sub.add_parser(
        "run",
        help="run the pipeline on a source (camera, replay, synthetic)",
        description="Run the AR pipeline on frames from SOURCE_URL (default: [source] url): oakd://, "
        "v4l2:///dev/videoN, replay://SESSION, synthetic://SCENE. Ctrl-C stops cleanly.",
    )
    p.add_argument("source_url", nargs="?", metavar="SOURCE_URL", help="frame source (default: [source] url)")
    _add_source_flags(p)
    _add_output_flags(p)
    p.set_defaults(func=cmd_run)

    p = sub.add_parser(
        "replay",
        help="run the pipeline on a recorded session",
        description="Replay the session folder SESSION through the pipeline (same as run replay://SESSION). "
        "--check only validates the session and lists every problem.",
    )
    p.add_argument("session", metavar="SESSION", help="session folder (made by `illuminet record` or --record)")
    p.add_argument(
        "--check",
        action="store_true",
        help="validate every index line and decode every frame; print problems; exit 1 if any",
    )
    _add_source_flags(p)
    _add_output_flags(p)
    p.set_defaults(func=cmd_replay)

    p = sub.add_parser(
        "record",
        help="record a source into a session folder",
        description="Record frames from SOURCE_URL (colour, 16-bit depth, timestamps, intrinsics, exposure, "
        "IMU) into the new session folder OUT. Crash-safe: a killed recording keeps every "
        "complete frame. Ctrl-C / SIGTERM stop and finalise it.",
    )
    p.add_argument("source_url", metavar="SOURCE_URL", help="frame source to record")
    p.add_argument("out", metavar="OUT", help="new (or empty) session folder")
    p.add_argument(
        "--color",
        choices=("raw", "png", "jpeg"),
        help="colour encoding: raw bytes (lossless, least CPU; default), PNG (lossless, ~40%% smaller), "
        "JPEG (lossy) ([output] record_color)",
    )
    p.add_argument("--jpeg-quality", type=int, metavar="Q", help="JPEG quality 1..100 ([output] record_jpeg_quality)")
    p.add_argument(
        "--no-fsync",
        action="store_true",
        help="do not fsync each frame (faster; still safe against kill -9, not against power loss)",
    )
    _add_source_flags(p)
    _add_output_flags(p, record=False)
    p.set_defaults(func=cmd_record)


_FLAG_KEYS = {
    "timing": ("source", "timing"),
    "loop": ("source", "loop"),
    "max_frames": ("source", "max_frames"),
    "video": ("output", "video"),
    "fps": ("output", "fps"),
    "png_dir": ("output", "png_dir"),
    "record": ("output", "record"),
    "mjpeg": ("output", "mjpeg"),
    "listen": ("output", "listen"),
    "port": ("output", "port"),
    "estimates": ("output", "estimates"),
    "viewer_model": ("output", "viewer_model"),
    "strict": ("logging", "strict"),
    "stats_json": ("logging", "stats_json"),
    "color": ("output", "record_color"),
    "jpeg_quality": ("output", "record_jpeg_quality"),
}


def config_with_flags(args: argparse.Namespace, cfg: Config) -> Config:
    """``cfg`` with every flag the user gave applied as an override (validated like the file)."""
    overrides = [(*_FLAG_KEYS[k], v) for k, v in vars(args).items() if k in _FLAG_KEYS and v is not None]
    if getattr(args, "no_fsync", False):
        overrides.append(("output", "record_fsync", False))
    cfg = apply_overrides(cfg, overrides)
    note_server_flags(args, cfg)
    return cfg


def note_server_flags(args: argparse.Namespace, cfg: Config) -> None:
    """One note for server flags given without ``--mjpeg`` (they were silently unused, even a
    ``--viewer-model`` naming a missing file)."""
    given = [
        f"--{k.replace('_', '-')}" for k in ("viewer_model", "listen", "port") if getattr(args, k, None) is not None
    ]
    if given and not cfg.output.mjpeg:
        many = len(given) > 1
        print(
            f"illuminet: note: {', '.join(given)} appl{'y' if many else 'ies'} to the --mjpeg server only; "
            f"without --mjpeg {'they are' if many else 'it is'} not used",
            file=sys.stderr,
        )


def report_stream(cfg: Config):
    """Where a run's report goes: stdout, or stderr when ``--estimates -`` streams JSON lines to stdout
    or ``--stats-json -`` writes the statistics there (a report mixed into them broke every JSON reader
    downstream)."""
    return sys.stderr if "-" in (cfg.output.estimates, cfg.logging.stats_json) else sys.stdout


def write_stats_json(cfg: Config, stats) -> None:
    """``[logging] stats_json``: the statistics as JSON, to the file or (``-``) to stdout. OSError
    propagates (the caller names the option)."""
    if cfg.logging.stats_json == "-":
        sys.stdout.write(stats.to_json() + "\n")
        sys.stdout.flush()
    else:
        from illuminet.runtime.files import written_whole

        # beside, then moved into place: a kill while writing leaves the previous file whole
        with written_whole(cfg.logging.stats_json) as tmp:
            tmp.write_text(stats.to_json() + "\n")


def _execute(cfg: Config, url: str, *, with_stages: bool) -> int:
    from illuminet.hw import open_source
    from illuminet.hw.replay import session_folder
    from illuminet.pipeline import build_sinks, build_stages, check_output_paths

    # before any device or file is opened: every output path can be written (a statistics file in a
    # missing folder would otherwise lose the run's statistics at its end), and none is inside the
    # session a replay reads. Errors here and in the set-up below reach illuminet.cli.main, which
    # prints them as one line.
    check_output_paths(cfg, reads=session_folder(url))
    if with_stages:
        from illuminet.runtime.assets.bundle import resolve_bundle

        resolve_bundle(cfg.model.bundle)  # a missing bundle: one line now, not after the camera is open
    stats = LoopStats()
    source = open_source(url, cfg)
    sinks = build_sinks(cfg, stats=stats.snapshot, source_url=url)
    stages = build_stages(cfg) if with_stages else []
    rc = 0
    o = cfg.output
    no_output = not (o.video or o.png_dir or o.record or o.estimates or o.mjpeg or cfg.logging.stats_json)
    # a camera runs until Ctrl-C: a note only at the end came after all that time. Said once the first
    # frames are through (not before the source opens: a source that fails says only why)
    told = no_output and source.live
    status = StatusLine()  # a live line on a terminal; nothing when piped
    note = [told]

    def on_stats(snap: dict) -> None:
        if note[0] and snap.get("frames"):
            note[0] = False
            status.clear()  # the note on its own line, not inside the status line
            print(
                "illuminet: note: no output is given, so the frames are processed and dropped; add "
                "--video FILE, --png-dir DIR, --record DIR, --estimates FILE or --mjpeg",
                file=sys.stderr,
            )
        status.update(snap)

    # a signal in the cleanup after the loop (a second SIGTERM) must not lose the statistics file
    with signals_held():
        try:
            run_loop(
                source,
                stages,
                sinks,
                strict=cfg.logging.strict,
                max_frames=cfg.source.max_frames,
                stats=stats,
                on_stats=on_stats,
                stats_interval_s=0.5,
                **loop_options(cfg.loop),
            )
        except IllumiNetError as e:  # these messages say it all; no traceback
            status.close()
            if log.isEnabledFor(logging.DEBUG):
                log.debug("traceback of the error below", exc_info=e)
            print(f"illuminet: {e.one_line()}", file=sys.stderr)
            rc = e.exit_code
        except OSError as e:
            status.close()
            if cfg.logging.strict:  # strict: the traceback, as for any failure
                raise
            print(f"illuminet: {e}", file=sys.stderr)
            rc = 1
        finally:
            status.close()
            if stats.frames or stats.end_reason:
                print(stats.format_stats(), file=report_stream(cfg))
                # each stage's own counters, as the demo prints them (the serial IMU's skipped lines, the
                # planes' bad depth, the anchor's placements ...: docs/runtime.md points users here)
                print_stage_counters(stages, report_stream(cfg))
            if stats.frames and no_output and not told:
                # a first `illuminet run SOURCE` processed its frames and showed only a timing table: say why
                print(
                    "illuminet: no output was given, so the frames were processed and dropped; add --video FILE, "
                    "--png-dir DIR, --record DIR, --estimates FILE or --mjpeg",
                    file=sys.stderr,
                )
            if cfg.logging.stats_json:
                try:
                    write_stats_json(cfg, stats)
                    if cfg.logging.stats_json != "-":
                        print(f"statistics written to {cfg.logging.stats_json}", file=report_stream(cfg))
                except OSError as e:  # checked before the start; the folder went away during the run
                    where = cfg.logging.stats_json
                    print(f"illuminet: [logging] stats_json: cannot write {where}: {e}", file=sys.stderr)
                    rc = 1
    if stats.end_reason.startswith("source error"):
        rc = 1
    return rc or lost_frames_status(stats, "illuminet")


def print_stage_counters(stages, out) -> None:
    """Each stage's own counters, a line each (the demo's report and run's)."""
    for st in stages:
        counters = st.stats() if hasattr(st, "stats") else None
        if counters:
            print(f"  {st.name}: " + ", ".join(f"{k}={v}" for k, v in counters.items()), file=out)


def lost_frames_status(stats: LoopStats, who: str) -> int:
    """1 (and a line saying so) when an output lacks frames, else 0. The stream went on (a live stream
    survives a bad frame), but a PNG folder on a full disk failed all 40 frames and the run said 0."""
    if not stats.sink_failures:
        return 0
    print(
        f"{who}: {stats.sink_failures} frame(s) missing from an output (sink failures; the first of each kind is "
        "in the log above): exit status 1",
        file=sys.stderr,
    )
    return 1


def cmd_run(args: argparse.Namespace, cfg: Config) -> int:
    cfg = config_with_flags(args, cfg)
    return _execute(cfg, args.source_url or cfg.source.url, with_stages=True)


def _depth_summary(reader) -> str:
    """How a session stores depth, for ``replay --check``."""
    if not reader.has_depth:
        return "none"
    k = reader.depth_scale
    if k == 1:
        return "16-bit PNG mm"
    return f"16-bit PNG mm at {reader.width // k}x{reader.height // k} (1/{k}, upsampled nearest on replay)"


def cmd_replay(args: argparse.Namespace, cfg: Config) -> int:
    cfg = config_with_flags(args, cfg)
    if args.check:
        try:
            reader = SessionReader(args.session)
        except SessionError as e:
            print(f"illuminet: {e}", file=sys.stderr)
            return 1
        problems = reader.check()
        if len(reader) == 0:  # replay then fails: "nothing to play" is the session's problem
            problems = [*problems, "no intact frame: nothing to replay"]
        m = reader.manifest
        # a manifest's escape sequences went to the terminal as they were (clear the screen, fake "OK")
        source = printable(str(m.get("source") or "?"))
        print(
            f"{args.session}: {m['format']} v{m['version']}, {reader.width}x{reader.height}, colour "
            f"{reader.color_encoding}, depth {_depth_summary(reader)}, "
            f"{len(reader)} intact frames, {'finalised' if reader.finalized else 'NOT finalised'}, "
            f"source {source}"
        )
        est = reader.estimates()
        if est:
            print(f"  lighting estimates: {len(est)} of {len(reader)} frames (estimates.jsonl)")
        for p in problems:
            print(f"  problem: {p}")
        print("OK" if not problems else f"{len(problems)} problem(s)")
        return 0 if not problems else 1
    if not Path(args.session).is_dir():
        from illuminet.runtime.stream.session import session_hint

        print(
            f"illuminet: replay: {args.session} is not a folder (expected a recorded session)"
            + session_hint(args.session),
            file=sys.stderr,
        )
        return 1
    url = "replay://" + quote(str(args.session), safe="/")
    return _execute(cfg, url, with_stages=True)


def cmd_record(args: argparse.Namespace, cfg: Config) -> int:
    if args.estimates:
        print(
            "illuminet record: --estimates needs the lighting stages, which record does not run; use "
            "`illuminet run SOURCE --record OUT --estimates FILE` (the session then keeps them too)",
            file=sys.stderr,
        )
        return 2
    if not str(args.out).strip():
        # '' read as "no --record": the frames were processed, dropped, and the run exited 0
        raise OutputPathError("record: OUT is empty; expected the new session folder to record into, e.g. sessions/s1")
    args.record = args.out
    cfg = config_with_flags(args, cfg)
    return _execute(cfg, args.source_url, with_stages=False)


__all__ = ["register", "config_with_flags", "cmd_run", "cmd_replay", "cmd_record", "ConfigError"]
