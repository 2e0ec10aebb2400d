"""``illuminet demo``: the whole pipeline on a built-in default scene, to a video file, with figures.

One command shows what the project does without any hardware: the built-in default session (a
small recording of the synthetic RGB-D camera that ships with the package, ``illuminet/data/
demo_session``: a room lit by a near lamp, 1280x800 colour, depth stored at the stereo resolution
640x400, the camera orbiting the spot where the object stands; replayed as fast as possible, in a
loop) -> planes -> anchor -> plane light -> shading (the learned model of the bundle when it loads,
else the SH baseline fitted to the RGB-D frame; the demo prints which one drove the shading) ->
render (shadow, occlusion) -> ``out/demo.mp4`` plus a PNG still of the middle frame. At the end it
prints the per-stage timing table, each stage's counters and the peak resident memory.

This module also owns the default session: :func:`make_default_session` generates it
(``illuminet demo --make-default-session DIR [--seed N]``), deterministically per seed.

Exit codes: 0 done, 1 the source or an output failed, 2 configuration error.
"""

from __future__ import annotations

import argparse
import collections
import logging
import resource
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from illuminet.runtime.config import Config, apply_overrides
from illuminet.runtime.frame import Frame
from illuminet.runtime.scene import ANCHOR, COMPOSITE, PLANE_LIGHT, SHADING
from illuminet.runtime.stage import Sink, Stage

log = logging.getLogger("illuminet.demo")

#: the committed default session (package data), made by ``illuminet demo --make-default-session``
DEFAULT_SESSION = Path(__file__).resolve().parents[1] / "data" / "demo_session"
#: what the default session records: a near lamp (clear shading gradient and shadow direction),
#: 1280x800 colour, the camera orbiting the object once (so a looped replay has no jump)
DEFAULT_SESSION_SCENE = "lamp"
DEFAULT_SESSION_SEED = 3
DEFAULT_SESSION_FRAMES = 32
DEFAULT_SESSION_SIZE = (1280, 800)
#: depth stored at 1/2 of the colour size (640x400, the OAK-D's stereo resolution; format version 2)
DEFAULT_SESSION_DEPTH_SCALE = 2
#: colour JPEG quality of the default session (the committed folder stays small)
DEFAULT_SESSION_JPEG_QUALITY = 85
#: the synthetic camera the demo used before the default session existed (still accepted via --source)
SYNTHETIC_SOURCE = "synthetic://indoor?seed=0&frames={frames}&size=1280x800&path=orbit"


#: the demo's video when --out is not given
DEFAULT_VIDEO = "out/demo.mp4"


def default_session_source_url(seed: int = DEFAULT_SESSION_SEED, frames: int = DEFAULT_SESSION_FRAMES) -> str:
    """The ``synthetic://`` URL the default session records (see :func:`make_default_session`)."""
    w, h = DEFAULT_SESSION_SIZE
    return f"synthetic://{DEFAULT_SESSION_SCENE}?seed={int(seed)}&frames={int(frames)}&size={w}x{h}&path=orbit"


def default_source_url(session: Path | None = None) -> str:
    """``replay://`` URL of the default session, looped (the demo runs more frames than it holds)."""
    from urllib.parse import quote

    path = Path(session) if session is not None else DEFAULT_SESSION
    return f"replay://{quote(str(path.resolve()))}?loop=1"


#: peak resident memory the demo should stay under (MB); above it the demo says so
RSS_TARGET_MB = 600.0


def register(sub) -> None:
    p = sub.add_parser(
        "demo",
        help="the whole pipeline on the built-in default session, to a video",
        description="Run the AR pipeline (planes -> plane light -> shading -> render) on the built-in default "
        "session (a small recording of the synthetic RGB-D camera: a near lamp, 1280x800 colour, "
        "640x400 depth, looped; or --source URL) and write the composited stream to a video, with a PNG "
        "still, per-stage timing and peak memory. Says which shading it used (by default the object's "
        "precomputed radiance transfer of the frame's light estimate; the learned model or a baseline "
        "when configured or when no estimate exists).",
    )
    p.add_argument(
        "--frames",
        type=int,
        default=None,
        metavar="N",
        help="frames to process (default 90; with --mjpeg: until Ctrl-C)",
    )
    p.add_argument(
        "--out",
        default=None,
        metavar="PATH",
        help="video file to write (.mp4, .m4v, .mov, .mkv, .avi; default out/demo.mp4; --no-video for none)",
    )
    p.add_argument("--no-video", action="store_true", help="write no video file")
    p.add_argument("--png-dir", metavar="DIR", help="also write every output frame as a PNG into DIR")
    p.add_argument(
        "--still",
        metavar="PATH",
        help="PNG still of the middle frame (default: next to the video, NAME_still.png; '' for none)",
    )
    p.add_argument(
        "--source",
        metavar="URL",
        help="frame source instead of the built-in default session (e.g. replay://SESSION, "
        "synthetic://indoor?size=1280x800, oakd://)",
    )
    p.add_argument(
        "--make-default-session",
        metavar="DIR",
        help="(re)generate the built-in default session into the new folder DIR and exit "
        "(deterministic per --seed; the shipped one is illuminet/data/demo_session)",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=DEFAULT_SESSION_SEED,
        help=f"seed of --make-default-session (default {DEFAULT_SESSION_SEED}, the shipped session)",
    )
    p.add_argument("--stats-json", metavar="PATH", help="write the per-step timing statistics as JSON (- = stdout)")
    p.add_argument("--strict", action="store_true", help="stop at the first failing frame with a traceback")
    from illuminet.commands.run import add_live_output_flags

    add_live_output_flags(
        p.add_argument_group(
            "live outputs (with --mjpeg the session plays in real time, looped, until Ctrl-C unless --frames)"
        )
    )
    p.set_defaults(func=cmd_demo)


class StillSink(Sink):
    """Keeps what the demo reports: the shading methods seen, and a PNG still of frame ``index`` (the
    last frame when the stream ends before it: a source shorter than ``--frames``)."""

    name = "still"

    def __init__(self, path: str | None, index: int):
        self.path = Path(path) if path else None
        self.index = index
        self.methods: collections.Counter = collections.Counter()
        self.frames = 0
        self.composited = 0
        self.written: Path | None = None
        self.written_frame = -1
        self._last: np.ndarray | None = None  # the latest picture, until the still is written

    def write(self, frame: Frame) -> None:
        sh = frame.results.get(SHADING.name)
        self.methods[sh.method if sh is not None else "none"] += 1
        comp = frame.results.get(COMPOSITE.name)
        if comp is not None and comp is not frame.color:
            self.composited += 1
        if self.path is not None and self.written is None:
            pic = comp if comp is not None else frame.color
            if self.frames == self.index:
                self._write(pic, self.frames)
            else:
                self._last = pic.copy()
        self.frames += 1

    def _write(self, pic: np.ndarray, index: int) -> None:
        import cv2

        self.path.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(self.path), np.ascontiguousarray(pic[:, :, ::-1])):
            raise OSError(f"cannot write the still {self.path}")
        self.written, self.written_frame, self._last = self.path, index, None

    def close(self) -> None:
        """The stream ended before frame ``index``: the last frame is the still."""
        if self.written is None and self._last is not None:
            self._write(self._last, self.frames - 1)

    def stats(self) -> dict[str, Any]:
        return {"frames": self.frames, "composited": self.composited, "shading": dict(self.methods)}


class SHFallbackShading(Stage):
    """The demo's shading when the object's bundle cannot load: the classic SH baseline from RGB-D.

    Second-order spherical harmonics fitted to the shading of the frame's pixels
    (:func:`illuminet.runtime.groundtruth.baselines.fit_sh_from_rgbd`: normals from depth, irradiance =
    pi x radiance / assumed albedo), evaluated at the drawn object's own vertex normals (the
    renderer draws the same generated object then, one value per render vertex). The fit runs on a
    320-pixel-wide copy of the frame every ``every`` frames and is smoothed like the learned
    shading (``[model] temporal_smoothing``). Writes ``results["shading"]`` with method ``"sh"``.
    """

    name = "shading"
    requires = (ANCHOR, PLANE_LIGHT)
    provides = (SHADING,)

    def __init__(self, cfg: Config, normals: np.ndarray, every: int = 3):
        self.cfg = cfg
        self.normals = np.asarray(normals, dtype=np.float64)
        self.every = int(every)
        self.alpha = float(cfg.model.temporal_smoothing)
        self._coef: np.ndarray | None = None
        self.frames = 0
        self.fits = 0

    def process(self, frame: Frame) -> Frame:
        import cv2

        from illuminet.runtime.groundtruth.baselines import fit_sh_from_rgbd
        from illuminet.runtime.physics import linearize
        from illuminet.runtime.scene import ObjectShading
        from illuminet.runtime.stage import FrameError

        anchor, pl = self.require(frame, ANCHOR), self.require(frame, PLANE_LIGHT)
        if frame.depth is None:
            raise FrameError("the SH baseline needs depth")
        if self._coef is None or self.frames % self.every == 0:
            w, h = frame.size
            sw, sh = 320, max(2, int(round(320 * h / w)))
            col = cv2.resize(frame.color, (sw, sh), interpolation=cv2.INTER_AREA)
            dep = cv2.resize(frame.depth, (sw, sh), interpolation=cv2.INTER_NEAREST)
            intr = frame.intrinsics.scaled(sw, sh)
            try:
                coef = fit_sh_from_rgbd(
                    linearize(col),
                    dep,
                    intr,
                    self.cfg.plane_light.assumed_albedo,
                    R_obj_cam=anchor.R.T,
                    exposure_scale=max(pl.exposure_scale, 1e-12),
                    stride=1,
                    step=2,
                )
            except ValueError as e:
                raise FrameError(f"SH baseline: {e}") from None
            a = self.alpha if self._coef is not None else 0.0
            self._coef = coef if a == 0.0 else a * self._coef + (1.0 - a) * coef
            self.fits += 1
        self.frames += 1
        from illuminet.runtime.sh import sh_eval

        irr = sh_eval(self._coef, self.normals)
        return frame.with_result(SHADING, ObjectShading(irradiance=irr, method="sh"))

    def stats(self) -> dict[str, Any]:
        return {"mode": "sh (demo fallback: no bundle)", "frames": self.frames, "fits": self.fits}


def make_default_session(
    path: str | Path,
    *,
    seed: int = DEFAULT_SESSION_SEED,
    frames: int = DEFAULT_SESSION_FRAMES,
    progress: Callable[[int, int], None] | None = None,
) -> Path:
    """Generate the demo's default session into the new folder ``path``, deterministically per seed.

    Records :func:`default_session_source_url` (the synthetic camera's lamp scene at 1280x800, one
    orbit) with JPEG colour (quality :data:`DEFAULT_SESSION_JPEG_QUALITY`) and depth stored at half
    the colour size (640x400 16-bit PNG, zlib level 9; session format version 2). The depth is the
    one the same synthetic scene gives at 640x400 (same seed: same room, lights and camera path;
    disparity noise and steps of a 640x400 stereo pair, as an OAK-D computes it), not a subsample of
    the 1280x800 depth, whose finer disparity noise would double the files. Host timestamps are
    the device ones (a synthetic frame has no host clock), so the frame files and the index are the
    same bytes for the same seed; only the manifest's ``created``/``closed`` times differ. The
    manifest's ``meta`` records the command and the seed. ``progress(done, frames)`` is called after
    each frame is written (rendering both sizes takes ~1 s a frame on 2 cores).

    Raises
    ------
    SessionError
        When ``path`` already holds a session.
    """
    import cv2

    from illuminet.hw import open_source
    from illuminet.runtime.config import defaults
    from illuminet.runtime.stream.session import SessionWriter

    url = default_session_source_url(seed, frames)
    w, h = DEFAULT_SESSION_SIZE
    k = DEFAULT_SESSION_DEPTH_SCALE
    stereo_url = url.replace(f"size={w}x{h}", f"size={w // k}x{h // k}")
    meta = {
        "generated_by": f"illuminet demo --make-default-session DIR --seed {int(seed)}",
        "seed": int(seed),
        "source": url,
        "frames": int(frames),
        "color_jpeg_quality": DEFAULT_SESSION_JPEG_QUALITY,
        "depth_scale": DEFAULT_SESSION_DEPTH_SCALE,
    }
    meta["depth_source"] = stereo_url
    with (
        open_source(url, defaults()) as src,
        open_source(stereo_url, defaults()) as stereo,
        SessionWriter(
            path,
            source=url,
            color="jpeg",
            jpeg_quality=DEFAULT_SESSION_JPEG_QUALITY,
            fsync=False,
            depth_scale=k,
            depth_png_compression=9,
            meta=meta,
        ) as wr,
    ):
        done = 0
        if progress is not None:
            progress(done, int(frames))
        while True:
            f, d = src.read(), stereo.read()
            if f is None or d is None:
                break
            # nearest-neighbour up to colour size: the writer's 1/k subsample gives back exactly these samples
            depth = cv2.resize(d.depth, (w, h), interpolation=cv2.INTER_NEAREST)
            wr.append(f.replace(depth=depth, t_host_ns=f.t_device_ns))
            done += 1
            if progress is not None:
                progress(done, int(frames))
    return Path(path)


def demo_stages(cfg: Config) -> list[Stage]:
    """The standard chain (:func:`illuminet.pipeline.build_stages`), with the SH baseline for shading
    when the bundle ``[model] bundle`` cannot be loaded (a built-in object is then drawn from its
    generator; see :class:`SHFallbackShading`)."""
    from illuminet.pipeline import build_stages
    from illuminet.runtime.assets.bundle import load_bundle

    stages = build_stages(cfg)
    spec = cfg.model.bundle
    if cfg.model.shading not in ("auto", "model"):
        return stages
    try:
        load_bundle(spec, verify=False)
    except ValueError as e:
        if not str(spec).startswith("builtin:"):
            raise
        from illuminet.runtime.assets.objects import load_object
        from illuminet.runtime.render.mesh import load_render_mesh

        # the object first: an unknown one fails with its own line, not after "the SH baseline drives it"
        normals = load_render_mesh(load_object(spec)).normals
        print(f"demo: the learned model is not available ({e}); the SH baseline drives the shading")
        stages = [SHFallbackShading(cfg, normals) if st.name == "shading" else st for st in stages]
    return stages


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, MB (Linux reports ru_maxrss in KiB)."""
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / 1024.0 if sys.platform != "darwin" else r / (1024.0 * 1024.0)


def describe_shading(methods: collections.Counter, cfg: Config) -> str:
    """One line saying what drove the object's shading, e.g. ``learned model (int8 ONNX)``."""
    if not methods:
        return "no frames"
    main, n = methods.most_common(1)[0]
    names = {
        "sh": "SH baseline (2nd-order spherical harmonics fitted to the RGB-D shading)",
        "ambient": "ambient baseline (the plane's mean irradiance: no learned model loaded, or a PRT-only bundle "
        "without a light estimate)",
        "constant": "constant-prior baseline",
        "none": "none (no plane light yet)",
        "prt": "precomputed radiance transfer of the light estimate (physical, self-shadowed)",
    }
    what = f"learned model ({main.split(':', 1)[1]} ONNX)" if main.startswith("model") else names.get(main, main)
    others = ", ".join(f"{m} {c}" for m, c in methods.items() if m != main)
    return f"{what} on {n} frames" + (f" (also: {others})" if others else "") + f"; [model] bundle = {cfg.model.bundle}"


def demo_frames(args: argparse.Namespace) -> int:
    """Frames the demo processes: --frames, else 90, else (serving --mjpeg) 0 = until Ctrl-C."""
    if args.frames is not None:
        return int(args.frames)
    return 0 if getattr(args, "mjpeg", None) else 90


def demo_config(args: argparse.Namespace, cfg: Config) -> Config:
    """The configuration the demo runs with: outputs from the flags, replay as fast as possible
    (in real time while serving ``--mjpeg``: a viewer wants the scene's pace, not a blur)."""
    live = bool(getattr(args, "mjpeg", None))
    over = [
        ("output", "video", "" if args.no_video else (args.out or DEFAULT_VIDEO)),
        ("source", "timing", "recorded" if live else "asap"),
        ("source", "max_frames", demo_frames(args)),
    ]
    for flag, key in (
        ("estimates", "estimates"),
        ("mjpeg", "mjpeg"),
        ("listen", "listen"),
        ("port", "port"),
        ("viewer_model", "viewer_model"),
    ):
        if getattr(args, flag, None) is not None:
            over.append(("output", key, getattr(args, flag)))
    if args.png_dir:
        over.append(("output", "png_dir", args.png_dir))
    if args.strict:
        over.append(("logging", "strict", True))
    if args.stats_json:
        over.append(("logging", "stats_json", args.stats_json))
    from illuminet.commands.run import note_server_flags

    cfg = apply_overrides(cfg, over)
    note_server_flags(args, cfg)
    return cfg


def cmd_demo(args: argparse.Namespace, cfg: Config) -> int:
    from illuminet.commands.run import lost_frames_status, report_stream
    from illuminet.hw import SourceError, open_source
    from illuminet.hw.replay import session_folder
    from illuminet.pipeline import build_sinks, check_creatable, check_output_paths, session_root
    from illuminet.runtime.errors import OutputPathError
    from illuminet.runtime.stream.loop import LoopStats, loop_options, run_loop, signals_held
    from illuminet.runtime.stream.sinks import SinkError

    for flag, value, expected in (
        ("--out", args.out, "a video file; leave --out out for out/demo.mp4, or --no-video for none"),
        ("--source", args.source, "a frame source URL; leave --source out for the built-in session"),
        ("--make-default-session", args.make_default_session, "the new folder to write the session into"),
    ):
        if value is not None and not value.strip():  # read as not given: the demo ran as without the flag
            print(f"illuminet demo: {flag} {value!r} is empty; expected {expected}", file=sys.stderr)
            return 2
    if args.make_default_session:
        return _make_session(args)
    if args.seed != DEFAULT_SESSION_SEED:
        print(
            f"illuminet demo: --seed {args.seed} only applies with --make-default-session DIR "
            f"(the demo replays the shipped session, seed {DEFAULT_SESSION_SEED})",
            file=sys.stderr,
        )
        return 2
    if args.frames is not None and args.frames < 1:
        print(f"illuminet demo: --frames must be at least 1, got {args.frames}", file=sys.stderr)
        return 2
    if args.no_video and args.out is not None:
        # --out was ignored without a word, and the still went to out/demo_still.png, not beside it
        print(
            f"illuminet demo: --out {args.out} names the video and --no-video writes none; drop one of them "
            "(--still PATH places the still picture)",
            file=sys.stderr,
        )
        return 2
    if args.out is None:
        args.out = DEFAULT_VIDEO
    frames = demo_frames(args)
    cfg = demo_config(args, cfg)
    url = _source_url(args, frames)
    still = _still_path(args)
    if still:
        import cv2

        if Path(still).is_dir() or not cv2.haveImageWriter(still):
            print(
                f"illuminet demo: --still {still}: expected an image file path (.png, .jpg); "
                f"{'it is a folder' if Path(still).is_dir() else 'OpenCV cannot write that extension'}",
                file=sys.stderr,
            )
            return 2
    probe = StillSink(still, index=(frames or 90) // 2)
    stats = LoopStats()
    report = report_stream(cfg)
    try:
        if cfg.output.video and session_root(Path(cfg.output.video).resolve().parent) is None:
            # the default out/demo.mp4 must work in a fresh checkout: the video sink does not make folders
            folder = Path(cfg.output.video).parent
            check_creatable(folder, f"--out {cfg.output.video}: cannot create its folder")
            try:
                folder.mkdir(parents=True, exist_ok=True)
            except OSError as e:
                raise OutputPathError(
                    f"--out {cfg.output.video}: cannot create its folder {folder} ({e.strerror}); "
                    "choose another --out (or --no-video)"
                ) from None
        # before the source opens: no output inside a recording, every output's folder writable
        check_output_paths(cfg, reads=session_folder(url), also=(("--still", still),) if still else ())
        source = open_source(url, cfg)
        stages = demo_stages(cfg)
        sinks = build_sinks(cfg, stats=stats.snapshot, source_url=url) + [probe]
    except OutputPathError as e:
        print(f"illuminet demo: {e}", file=sys.stderr)
        return 2
    except (SourceError, SinkError, ValueError, OSError) as e:
        print(f"illuminet demo: {e}", file=sys.stderr)
        return getattr(e, "exit_code", 1)  # a malformed --source URL is a usage mistake (2), as for run
    print(f"demo: source {url}", file=report)
    rc = 0
    from illuminet.progress import StatusLine

    status = StatusLine()  # a live line on a terminal; nothing when piped
    # a signal in the cleanup after the loop (a second SIGTERM) must not lose the report or --stats-json
    with signals_held():
        try:
            run_loop(
                source,
                stages,
                sinks,
                strict=cfg.logging.strict,
                max_frames=frames,
                stats=stats,
                on_stats=status.update,
                stats_interval_s=0.5,
                **loop_options(cfg.loop),
            )
        except (SourceError, SinkError, OSError) as e:
            status.close()
            if cfg.logging.strict:
                raise
            print(f"illuminet demo: {e}", file=sys.stderr)
            rc = 1
        finally:
            status.close()
            if rc == 0 or stats.frames:  # a source that failed to open leaves its one line, not a report of nothing
                _print_report(stats, stages, probe, cfg, rc, report)
    if stats.end_reason.startswith("source error"):
        rc = 1
    return rc or lost_frames_status(stats, "illuminet demo")


def _make_session(args: argparse.Namespace) -> int:
    """``--make-default-session DIR``: write the default session and exit."""
    from illuminet.hw import SourceError
    from illuminet.models.train import Progress
    from illuminet.runtime.stream.session import SessionError

    bar = None

    def progress(done: int, total: int) -> None:
        nonlocal bar
        if bar is None:  # the folder is created: ~1 s a frame (each rendered at 1280x800 and 640x400)
            print(
                f"illuminet demo: rendering {total} frames of {default_session_source_url(args.seed)} into "
                f"{args.make_default_session} (about {total} s on 2 cores)",
                file=sys.stderr,
            )
            bar = Progress("default session", total)
        bar(done, total)

    try:
        out = make_default_session(args.make_default_session, seed=args.seed, progress=progress)
    except (SourceError, SessionError, OSError) as e:
        print(f"illuminet demo: --make-default-session: {e}", file=sys.stderr)
        return 1
    print(f"default session: {out} ({default_session_source_url(args.seed)}, seed {args.seed})")
    return 0


def _source_url(args: argparse.Namespace, frames: int | None) -> str:
    """--source, else the shipped default session, else the synthetic camera."""
    if args.source:
        return args.source
    if (DEFAULT_SESSION / "manifest.json").is_file():
        return default_source_url()
    # an install without the package data: the synthetic camera still gives a demo
    print(
        f"demo: the default session {DEFAULT_SESSION} is missing; using the synthetic camera "
        f"(slow: it renders every frame)"
    )
    return SYNTHETIC_SOURCE.format(frames=frames or 100000)


def _still_path(args: argparse.Namespace) -> str:
    """--still, else next to the video (NAME_still.png), else out/demo_still.png."""
    if args.still is not None:
        return args.still
    if not args.no_video:
        p = Path(args.out or DEFAULT_VIDEO)
        return str(p.with_name(p.stem + "_still.png"))
    return "out/demo_still.png"


def _print_report(stats, stages, probe: StillSink, cfg: Config, rc: int, out=None) -> None:
    """The end-of-run report: timing table, stage statistics, shading used, outputs, peak memory
    (to ``out``, default stdout)."""
    from illuminet.commands.run import print_stage_counters

    out = out or sys.stdout
    print(stats.format_stats(), file=out)
    print_stage_counters(stages, out)
    print(f"shading: {describe_shading(probe.methods, cfg)}", file=out)
    if cfg.output.video and rc == 0:
        print(f"video: {cfg.output.video}", file=out)
    if probe.written is not None:
        early = probe.written_frame < probe.index
        # else Ctrl-C / SIGTERM, or an output whose reader left (--estimates - | head)
        ended = stats.end_reason == "end of stream" or stats.end_reason.startswith("source error")
        why = "the source ended first" if ended else "the run was stopped first"
        print(
            f"still: {probe.written}" + (f" (the last frame, {probe.written_frame}: {why})" if early else ""),
            file=out,
        )
    rss = peak_rss_mb()
    print(
        f"peak resident memory: {rss:.0f} MB (target <= {RSS_TARGET_MB:.0f} MB)"
        + ("" if rss <= RSS_TARGET_MB else "  ** over target **"),
        file=out,
    )
    if cfg.logging.stats_json:
        try:
            from illuminet.commands.run import write_stats_json

            write_stats_json(cfg, stats)
        except OSError as e:  # checked before the start; the folder went away during the run
            print(f"illuminet demo: --stats-json: cannot write {cfg.logging.stats_json}: {e}", file=sys.stderr)
