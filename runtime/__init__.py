"""The per-frame runtime. This folder is the floor of the layering: it imports nothing from hw/,
models/, calibration/ or the entry package.

``runtime/*.py`` (the floor everyone stands on)
    ``frame`` (Frame, Intrinsics, Exposure), ``scene`` (result types and the declared result keys:
    the contracts between stages), ``stage`` (life cycle, contracts check, the one failure policy),
    ``physics`` (linear RGB, OI, Lambert), ``sh`` (spherical-harmonics maths), ``config``;
    ``relight`` (the one-shot relight API, which runs the stages on one image).
``stages/``
    The per-frame stages in pipeline order: planes, anchor (+ odometry), plane light, shading.
``render/``
    GL context, meshes, shaders, compositor passes, cast shadow, and the render stage.
``stream/``
    The loop (flow limiting, failures, signals), timing, sinks, MJPEG server, session format.
``assets/``
    Built-in and user meshes, object bundles.
``groundtruth/``
    Light transport, exact visibility and baselines, for the synthetic camera, training and
    evaluation only (no stage imports it).
"""
