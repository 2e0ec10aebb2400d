"""The per-frame stages, in pipeline order: planes -> anchor (+ odometry) -> plane light -> shading.

Each module owns one :class:`~illuminet.runtime.stage.Stage` and the maths only it uses. Stages import
the floor (``illuminet.runtime``: frame, scene contracts, physics, config, SH maths) and each other's
result types, never ground truth (``illuminet.runtime.groundtruth``) nor the command line.
"""
