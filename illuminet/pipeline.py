"""Assembles the standard AR pipeline from the configuration: the stages in order, and the sinks.

Filled in as the stages land; the commands (run, replay, demo) all build their pipeline here so
that they process frames identically.
"""

from __future__ import annotations

from illuminet.runtime.config import Config
from illuminet.runtime.stage import Stage


def build_stages(cfg: Config) -> list[Stage]:
    """Planes -> anchor -> plane light -> shading -> render, as configured."""
    return []
