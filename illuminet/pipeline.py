"""Assembles the standard AR pipeline from the configuration: the stages in order, and the sinks.

The commands (run, replay, demo, relight's stages) all build their pipeline here so that they process
frames identically; :func:`chain_diagram` draws the chain with each stage's declared contract (what
``illuminet config --pipeline`` prints and ``docs/architecture.md`` shows).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from illuminet.runtime.config import Config, ConfigError
from illuminet.runtime.errors import OutputPathError
from illuminet.runtime.stage import Sink, Stage
from illuminet.runtime.stream.sinks import EstimateSink, PngSequenceSink, SessionRecorderSink, VideoSink


def build_stages(cfg: Config, *, render: bool = True) -> list[Stage]:
    """Planes -> anchor -> plane light -> light estimate -> shading -> render, as configured (unopened).

    Parameters
    ----------
    cfg : Config
        All sections; ``[source] response_curve`` (when set) is loaded once and given to both the
        plane measurement (to linearise) and the renderer (to encode the object the same way).
    render : bool
        Include the :class:`~illuminet.runtime.render.stage.RenderStage` (False: lighting only, e.g.
        for evaluation or benchmarks of the lighting stages alone).
    """
    from illuminet.hw.serial_imu import ImuStage
    from illuminet.runtime.physics import load_response_lut
    from illuminet.runtime.stages.anchor import AnchorStage
    from illuminet.runtime.stages.plane_light import PlaneLightStage
    from illuminet.runtime.stages.planes import PlaneStage
    from illuminet.runtime.stages.shading import ShadingStage

    try:
        lut = load_response_lut(cfg.source.response_curve) if cfg.source.response_curve else None
    except ValueError as e:  # a missing or unreadable file: the configuration's mistake, one line
        raise ConfigError(f"[source] response_curve: {e}") from None
    stages: list[Stage] = []
    imu = ImuStage.from_config(cfg)  # a serial IMU ([imu] url) attaches gravity before planes need it
    if imu is not None:
        stages.append(imu)
    # full_masks=False: no stage of this chain reads Plane.inlier_mask at full resolution (the anchor
    # uses the cloud-resolution cloud_mask); upsampling one mask per plane cost ~1.4 ms per 1280x800
    # frame (profile of `illuminet bench demo`)
    stages += [PlaneStage(cfg, full_masks=False), AnchorStage(cfg), PlaneLightStage(cfg, response_lut=lut)]
    if cfg.light.enabled:
        from illuminet.runtime.stages.light_estimate import LightEstimateStage

        stages.append(LightEstimateStage(cfg, response_lut=lut))
    stages.append(ShadingStage(cfg))
    if render:
        from illuminet.runtime.render.stage import RenderStage

        stages.append(RenderStage(cfg, response_lut=lut))
    return stages


#: output keys whose file is written into an existing folder: (section, key, what it is)
_OUTPUT_FILES = (
    ("output", "video", "video file"),
    ("output", "estimates", "estimates file"),
    ("logging", "stats_json", "statistics file"),
)
#: output keys naming a folder the run creates (with its parents) when missing
_OUTPUT_DIRS = (
    ("output", "png_dir", "PNG folder"),
    ("output", "record", "session folder"),
)


def session_root(path: Path) -> Path | None:
    """The recorded session folder ``path`` is (or is inside), else None: the nearest folder, from
    ``path`` up, holding a ``manifest.json`` and an index (``frames.jsonl``) or a ``frames/`` folder.

    Not the manifest's contents: a session whose manifest a crash left torn is still a recording."""
    from illuminet.runtime.stream.session import INDEX, MANIFEST

    for d in (path, *path.parents):
        if (d / MANIFEST).is_file() and ((d / INDEX).exists() or (d / "frames").is_dir()):
            return d
    return None


def check_output_paths(cfg: Config, reads: Path | None = None, also: tuple[tuple[str, str], ...] = ()) -> None:
    """Refuse, before anything is opened, every configured output that could not be written, or that
    would write into a recording: ``reads`` (the session folder a replay reads), any other recorded
    session on disk (:func:`session_root`), or the session this run records (``[output] record``).
    An estimates or statistics file named like one of a session's own files replaced its index or
    manifest, and PNGs were added to its frames.

    ``also``: more output files as (what the user typed, path), e.g. ``("--still", "out/x.png")``.

    A statistics file is written only at the end of a run, so a typo in its folder would otherwise
    lose the whole run's statistics; a video or estimates file in a missing folder fails only after
    the source (a camera) is open. Files need their folder to exist; folders the run creates need
    their nearest existing ancestor to be a writable folder.

    Raises
    ------
    OutputPathError
        One line naming the key, the path and the fix.
    """
    if cfg.output.estimates == "-" and cfg.logging.stats_json == "-":
        raise OutputPathError(
            "[logging] stats_json: - (standard output) is where --estimates - writes its JSON lines; give the "
            "statistics a file (--stats-json FILE)"
        )
    inside = reads.resolve() if reads is not None else None
    record = Path(cfg.output.record).resolve() if cfg.output.record else None
    named = [(f"[{section}] {key}", key, cfg[section][key]) for section, key, _ in _OUTPUT_FILES + _OUTPUT_DIRS]
    taken: dict[Path, str] = {}  # each output's resolved path -> the option that writes it
    for label, key, value in named + [(flag, "also", value) for flag, value in also]:
        if not value or (key in ("estimates", "stats_json") and value == "-"):
            continue
        p = Path(value).resolve()
        if p in taken:
            # two outputs on one file: the last to close replaced the other (--video x --estimates x kept
            # the video; --estimates x --stats-json x lost every estimate), with exit status 0
            raise OutputPathError(
                f"{label}: {value} is also the path of {taken[p]}; one output would overwrite the other: "
                "give each output its own path"
            )
        taken[p] = label
        if inside is not None and (p == inside or inside in p.parents):
            raise OutputPathError(
                f"{label}: {value} is inside the session being replayed ({reads}); writing there "
                "would change the recording: choose a path outside it"
            )
        if key != "record" and record is not None and (p == record or record in p.parents):
            raise OutputPathError(
                f"{label}: {value} is inside the session this run records ({cfg.output.record}); "
                "it would mix with the recording's own files: choose a path outside it"
            )
        root = session_root(p)
        # the record folder itself may be an existing session: the recorder refuses it with its own line
        if root is not None and not (key == "record" and root == p):
            raise OutputPathError(
                f"{label}: {value} is inside the recorded session {root}; writing there would damage the "
                "recording: choose a path outside it"
            )
    for section, key, what in _OUTPUT_FILES:
        value = cfg[section][key]
        if not value or (key in ("estimates", "stats_json") and value == "-"):
            continue
        path = Path(value)
        parent = path.parent if str(path.parent) else Path(".")
        if path.is_dir():
            article = "an" if what[0] in "aeiou" else "a"
            raise OutputPathError(f"[{section}] {key}: {value} is a folder; expected {article} {what} path")
        try:
            links = path.stat().st_nlink if path.is_file() else 1
        except OSError:
            links = 1
        if links > 1:
            # the file is truncated and rewritten in place: every other name of it changes too. A hard
            # link to a session's manifest.json or frames.jsonl replaced the recording's own files
            raise OutputPathError(
                f"[{section}] {key}: {value} has {links} hard links; writing it would also change the same file "
                "under its other names (a recording's manifest or index?): choose a new path"
            )
        if not parent.is_dir():
            raise OutputPathError(
                f"[{section}] {key}: folder {parent} of the {what} {value} does not exist; create it or "
                "choose another path"
            )
        if not os.access(parent, os.W_OK):
            raise OutputPathError(f"[{section}] {key}: folder {parent} of the {what} {value} is not writable")
    for section, key, what in _OUTPUT_DIRS:
        value = cfg[section][key]
        if not value:
            continue
        path = Path(value)
        if path.exists() and not path.is_dir():
            raise OutputPathError(f"[{section}] {key}: {value} exists and is not a folder; expected a {what}")
        check_creatable(path, f"[{section}] {key}: cannot create the {what} {value}")
    # the extra files (the demo's --still) are written into a folder made for them when missing
    for flag, value in also:
        if value:
            check_creatable(Path(value).parent, f"{flag} {value}: cannot create its folder")


def check_creatable(path: Path, what: str) -> None:
    """Refuse ``path`` (a folder, made with its parents) when its nearest existing ancestor is not a
    writable folder: ``what`` begins the one-line message."""
    ancestor = path if str(path) else Path(".")
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if ancestor.exists() and not ancestor.is_dir():
        raise OutputPathError(f"{what}: {ancestor} is a file, not a folder; choose another path")
    if ancestor.exists() and not os.access(ancestor, os.W_OK):
        raise OutputPathError(f"{what}: {ancestor} is not a writable folder; choose another path")


def build_sinks(
    cfg: Config,
    *,
    stats: Callable[[], dict[str, Any]] | None = None,
    source_url: str | None = None,
) -> list[Sink]:
    """The outputs the ``[output]`` section asks for (unopened), in a fixed order.

    Parameters
    ----------
    cfg : Config
        ``output.video`` -> :class:`~illuminet.runtime.stream.sinks.VideoSink` (at ``output.fps``),
        ``output.png_dir`` -> :class:`~illuminet.runtime.stream.sinks.PngSequenceSink`,
        ``output.record`` -> :class:`~illuminet.runtime.stream.sinks.SessionRecorderSink`
        (``record_color``, ``record_jpeg_quality``, ``record_fsync``),
        ``output.estimates`` -> :class:`~illuminet.runtime.stream.sinks.EstimateSink` (JSONL),
        ``output.mjpeg`` -> ``illuminet.runtime.stream.mjpeg.MjpegSink`` on ``listen``:``port``
        (its ``/viewer`` draws ``output.viewer_model``, default the ``[model] bundle``'s built-in
        object, else ``builtin:vase``; at most ``max_clients`` connections, ``Host`` checked against
        ``allowed_hosts``).
    stats : callable, optional
        Returns live loop figures (``LoopStats.snapshot``) for the MJPEG status page.
    source_url : str, optional
        Stored in recorded sessions' manifests (default ``cfg.source.url``).

    Returns
    -------
    list of Sink
        Possibly empty (then frames are processed and only the statistics are printed).
    """
    out = cfg.output
    sinks: list[Sink] = []
    if out.record:
        if not 1 <= out.record_jpeg_quality <= 100:
            raise ConfigError(
                f"[output] record_jpeg_quality: expected an int in 1..100, got {out.record_jpeg_quality!r}"
            )
        sinks.append(
            SessionRecorderSink(
                out.record,
                source=source_url if source_url is not None else cfg.source.url,
                color=out.record_color,
                jpeg_quality=out.record_jpeg_quality,
                fsync=out.record_fsync,
            )
        )
    if out.video:
        sinks.append(VideoSink(out.video, fps=out.fps))
    if out.png_dir:
        sinks.append(PngSequenceSink(out.png_dir))
    if out.estimates:
        sinks.append(EstimateSink(out.estimates))
    if out.mjpeg:
        from illuminet.runtime.stream.mjpeg import MjpegSink

        bundle = str(cfg.model.bundle)
        model = out.viewer_model or (bundle if bundle.startswith("builtin:") else "builtin:vase")
        try:
            sinks.append(
                MjpegSink(
                    out.listen,
                    out.port,
                    stats=stats,
                    viewer_model=model,
                    object_scale=cfg.render.object_scale,
                    max_clients=out.max_clients,
                    allowed_hosts=out.allowed_hosts,
                )
            )
        except ValueError as e:  # the viewer model: a one-line message naming the key
            raise ConfigError(str(e)) from None
    return sinks


def chain_diagram(stages: list[Stage]) -> str:
    """The chain as text: one line of stage names, then each stage's requires / optional / provides.

    Generated from the stages' declared contracts, so it cannot disagree with the code;
    ``tests/test_contracts.py`` checks that docs/architecture.md holds the default chain's diagram.
    """
    line = "Source ──Frame──▶ " + " ──▶ ".join(s.name for s in stages) + " ──▶ Sinks"
    rows = [("stage", "class", "requires", "optional", "provides")]
    for s in stages:
        rows.append(
            (
                s.name,
                type(s).__name__,
                ", ".join(k.name for k in s.requires) or "-",
                ", ".join(k.name for k in s.optional) or "-",
                ", ".join(k.name for k in s.provides) or "-",
            )
        )
    w = [max(len(r[i]) for r in rows) for i in range(5)]
    table = ["  ".join(c.ljust(w[i]) for i, c in enumerate(r)).rstrip() for r in rows]
    return "\n".join([line, ""] + table)
