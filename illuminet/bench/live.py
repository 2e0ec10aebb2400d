"""``illuminet bench live``: a live camera faster than the pipeline never grows a queue or the latency.

The camera is the synthetic one in live mode (``synthetic://lamp?live=1&fps=N&size=WxH&path=orbit``:
frames rendered once, then delivered on the camera's own clock into an OAK-D-like queue of 2 that
drops the oldest). For each rate of ``--fps`` (default 60,120) the whole chain (planes -> anchor ->
plane light -> light -> shading -> render) runs for ``--seconds`` (default 10) in each loop mode of
``--pipeline`` (default: the ``[loop] pipeline`` setting), and the benchmark prints:

* frames delivered by the camera, processed, and dropped (by the loop's newest-frame slot, and by
  the camera's own queue), and the frame rate out;
* the latency from capture (the camera's host timestamp) to the composite handed to the sinks,
  median and p99 **per quarter of the run**, and the last quarter's median over the first's: flat
  when nothing queues up (on a loaded machine the quarters move with the load, both ways);
* the most frames that ever waited in the camera's queue and in the pipelined loop's hand-off
  (bounded by 2 and by ``[loop] depth``, whatever the rates);
* CPU time per processed frame (whole process).
"""

from __future__ import annotations

import numpy as np

from illuminet.runtime.config import ConfigError

DEFAULT_FPS = (60, 120)


def _rates(text: str | None) -> list[int]:
    if text is None:  # '' is a mistake, not "not given" (it ran the default rates)
        return list(DEFAULT_FPS)
    try:
        rates = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ConfigError(f"--fps: expected comma-separated integers such as 60,120, got {text!r}") from None
    if not rates or any(not 1 <= r <= 1000 for r in rates):
        raise ConfigError(f"--fps: each rate must be 1..1000 frames per second, got {text!r}")
    return rates


def check_args(args, cfg) -> tuple[list[int], float, tuple[int, int], list[str]]:
    """This benchmark's flags (rates, seconds per rate, size, modes); ``illuminet bench`` calls it
    before any benchmark runs, so a mistake is refused before the header, whichever are named."""
    from illuminet.bench.demo import parse_modes, parse_size

    quick = bool(getattr(args, "quick", False))
    rates = _rates(getattr(args, "fps", None))
    given = getattr(args, "seconds", None)  # `or` took --seconds 0 for "not given": 10 s per rate, silently
    seconds = float(given) if given is not None else (3.0 if quick else 10.0)
    if not 0.5 <= seconds <= 3600:
        raise ConfigError(f"--seconds: expected 0.5..3600, got {seconds!r}")
    size = getattr(args, "size", None)
    size = parse_size("640x400" if size is None else size)
    return rates, seconds, size, parse_modes(getattr(args, "pipeline", None), cfg.loop.pipeline)


def quarters(values: list[float]) -> list[dict[str, float]]:
    """Median and p99 (ms) of each quarter of ``values`` (seconds, in order)."""
    a = np.asarray(values, dtype=np.float64) * 1e3
    out = []
    for part in np.array_split(a, 4):
        if part.size:
            out.append(
                {"n": int(part.size), "median_ms": float(np.median(part)), "p99_ms": float(np.percentile(part, 99))}
            )
    return out


def run(args, cfg) -> dict:
    from illuminet.commands.demo import demo_stages
    from illuminet.hw import open_source
    from illuminet.runtime.stage import Sink
    from illuminet.runtime.stream.loop import run_loop

    rates, seconds, (w, h), modes = check_args(args, cfg)

    class Null(Sink):
        name = "null"

        def write(self, frame) -> None:
            pass

    results = {}
    print(f"camera: synthetic lamp scene, live, {w}x{h}, orbiting; {seconds:g} s per rate and mode")
    for fps in rates:
        for mode in modes:
            n = int(round(fps * seconds))
            url = f"synthetic://lamp?seed=3&live=1&fps={fps}&frames={n}&size={w}x{h}&path=orbit"
            src = open_source(url, cfg)
            stats = run_loop(
                src,
                demo_stages(cfg),
                [Null()],
                install_signals=False,
                pipeline=mode,
                depth=int(cfg.loop.depth),
                opencv_threads=int(cfg.loop.opencv_threads),
            )
            d = stats.to_dict()
            s = d["source"]
            lat = stats.samples["latency"].values if "latency" in stats.samples else []
            q = quarters(lat)
            r = {
                "fps_camera": fps,
                "pipeline": d["pipeline"],
                "delivered": s.get("delivered", 0),
                "processed": d["frames"],
                "dropped_loop": d["dropped"],
                "dropped_camera_queue": s.get("dropped", 0),
                "fps_out": d["fps"],
                "latency_quarters": q,
                "latency_median_ms": d["steps"].get("latency", {}).get("median_ms", 0.0),
                "latency_p99_ms": d["steps"].get("latency", {}).get("p99_ms", 0.0),
                "camera_queue_max": s.get("queue_max", 0),
                "handoff_max": d["in_flight_max"],
                "cpu_ms_per_frame": d["cpu_ms_per_frame"],
                "failed_frames": d["failed_frames"],
            }
            results[f"{fps}fps-{mode}"] = r
            ratio = q[-1]["median_ms"] / q[0]["median_ms"] if len(q) == 4 and q[0]["median_ms"] > 0 else 0.0
            # what keeps the latency flat is structural: every queue between camera and sinks is bounded
            bounded = r["camera_queue_max"] <= src.queue and r["handoff_max"] <= max(1, int(cfg.loop.depth))
            r["latency_last_over_first_quarter"] = ratio
            r["queues_bounded"] = bounded
            print(
                f"{fps:>4} fps camera, {r['pipeline']:>7}: delivered {r['delivered']}, processed {r['processed']} "
                f"({r['fps_out']:.1f} fps out), dropped {r['dropped_loop']} by the loop + "
                f"{r['dropped_camera_queue']} by the camera queue; queue max {r['camera_queue_max']} "
                f"(camera, of {src.queue}), {r['handoff_max']} (hand-off); CPU {r['cpu_ms_per_frame']:.1f} ms per frame"
            )
            print(
                "      latency median / p99 per quarter: "
                + " | ".join(f"{x['median_ms']:.1f} / {x['p99_ms']:.1f}" for x in q)
                + f" ms; last quarter's median x{ratio:.2f} of the first's; queues "
                + ("bounded" if bounded else "NOT BOUNDED")
            )
    return results
