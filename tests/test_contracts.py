"""Declared stage contracts: the chain is checked when it is built, and one policy handles a failed
stage or a missing input (runtime/stage.py)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from illuminet.pipeline import build_stages, chain_diagram
from illuminet.runtime.config import apply_overrides, defaults
from illuminet.runtime.frame import Frame, Intrinsics
from illuminet.runtime.scene import ANCHOR, PLANES, RESULT_KEYS, SHADING
from illuminet.runtime.stage import FrameError, MissingInput, PipelineError, Stage, StageChain, check_chain

from .conftest import REPO


def _frame(seq=0):
    return Frame(
        seq=seq,
        t_device_ns=seq,
        t_host_ns=seq,
        color=np.zeros((4, 4, 3), np.uint8),
        depth=None,
        intrinsics=Intrinsics(1, 1, 1, 1, 4, 4),
    )


class _Producer(Stage):
    name = "producer"
    provides = (PLANES,)

    def __init__(self, fail_on=()):
        self.fail_on, self.n = set(fail_on), 0

    def process(self, frame):
        self.n += 1
        if frame.seq in self.fail_on:
            raise FrameError("bad frame")
        return frame.with_result(PLANES, (frame.seq,))


class _Consumer(Stage):
    name = "consumer"
    requires = (PLANES,)
    provides = (ANCHOR,)

    def __init__(self):
        self.seen = []

    def process(self, frame):
        planes = self.require(frame, PLANES)
        self.seen.append(planes)
        return frame.with_result(ANCHOR, planes)


def test_default_chain_is_wired_and_every_key_is_declared():
    stages = build_stages(defaults(), render=False)
    check_chain(stages)  # no error
    for st in stages:
        for k in (*st.requires, *st.optional, *st.provides):
            assert RESULT_KEYS[k.name] is k
    names = [s.name for s in stages]
    assert names == ["planes", "anchor", "plane_light", "light", "shading"]


def test_missing_producer_names_both_stages():
    with pytest.raises(PipelineError, match=r"stage 'consumer' requires results\['planes'\].*before 'consumer'"):
        check_chain([_Consumer()])
    with pytest.raises(
        PipelineError,
        match=r"stage 'consumer' reads results\['planes'\], which stage 'producer' "
        r"provides only after it: put 'producer' before 'consumer'",
    ):
        check_chain([_Consumer(), _Producer()])
    with pytest.raises(PipelineError, match=r"requires results\[.plane_light.\]"):
        StageChain([s for s in build_stages(defaults(), render=False) if s.name != "plane_light"])


def test_optional_input_provided_too_late_is_an_error():
    class _Reader(Stage):
        name = "reader"
        optional = (SHADING,)

    class _Late(Stage):
        name = "late"
        provides = (SHADING,)

    check_chain([_Reader()])  # nobody provides it: fine, it is optional
    with pytest.raises(PipelineError, match="put 'late' before 'reader'"):
        check_chain([_Reader(), _Late()])


def test_failure_keeps_last_good_and_skips_consumers_until_then(caplog):
    prod, cons = _Producer(fail_on={0, 2}), _Consumer()
    chain = StageChain([prod, cons])
    with caplog.at_level(logging.WARNING):
        out0 = chain(_frame(0))  # producer fails, no earlier result: consumer is skipped
        out1 = chain(_frame(1))
        out2 = chain(_frame(2))  # producer fails: its last good result (from frame 1) is carried
    assert PLANES.name not in out0.results and ANCHOR.name not in out0.results
    assert out1.results[PLANES.name] == (1,) and out2.results[PLANES.name] == (1,)
    assert cons.seen == [(1,), (1,)]
    assert caplog.text.count("stage:consumer: missing planes") == 1
    assert caplog.text.count("stage:producer: FrameError") == 1


def test_strict_chain_raises_the_missing_input():
    with pytest.raises(MissingInput, match=r"stage 'consumer' needs results\['planes'\]"):
        StageChain([_Consumer()], strict=True, check=False).run(_frame())


def test_chain_diagram_in_docs_is_the_real_chain():
    """docs/architecture.md (and the README's summary line) show the chain build_stages makes."""
    cfg = apply_overrides(defaults(), [])
    diagram = chain_diagram(_described(cfg))
    doc = (REPO / "docs" / "architecture.md").read_text()
    assert diagram in doc, "docs/architecture.md is stale: paste the output of `illuminet config --pipeline`"
    readme = (REPO / "README.md").read_text()
    line = " ──▶ ".join(s.name for s in _described(cfg))
    assert line in readme


def _described(cfg):
    return build_stages(cfg, render=True)


def test_keys_are_not_spelled_as_strings_outside_the_contracts():
    """Result keys are named through the declared ResultKey constants (runtime/scene.py)."""
    import ast

    bad = []
    for folder in ("runtime", "hw", "models", "illuminet"):
        for py in (REPO / folder).rglob("*.py"):
            if py.name == "scene.py" and py.parent.name == "runtime":
                continue
            tree = ast.parse(py.read_text())
            for node in ast.walk(tree):
                if (
                    isinstance(node, ast.Call)
                    and getattr(node.func, "attr", "") in ("with_result", "get")
                    and node.args
                    and isinstance(node.args[0], ast.Constant)
                    and node.args[0].value in RESULT_KEYS
                ):
                    if getattr(node.func, "attr", "") == "get" and "results" not in ast.unparse(node.func):
                        continue
                    bad.append(f"{py.relative_to(REPO)}:{node.lineno} {ast.unparse(node)}")
    assert not bad, "results keys spelled as strings:\n" + "\n".join(bad)
