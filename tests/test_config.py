"""Configuration: schema vs config.toml, validation messages, CLI overrides."""

from __future__ import annotations

import pytest

from illuminet.runtime import config as C

from .conftest import REPO


def test_config_toml_documents_every_key_with_its_default():
    cfg = C.load(REPO / "config.toml")
    assert cfg.to_dict() == C.defaults().to_dict()
    text = (REPO / "config.toml").read_text()
    for section, keys in C.SCHEMA.items():
        assert f"[{section}]" in text
        for key in keys:
            # every key is preceded by a comment line
            lines = text.splitlines()
            i = next(
                i
                for i, line in enumerate(lines)
                if line.startswith(f"{key} =") and f"[{section}]" in "\n".join(lines[:i])
            )
            assert lines[i - 1].startswith("#"), f"[{section}] {key} has no comment"


def test_unknown_key_is_refused_with_its_name(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text("[planes]\nmethd = 'ransac'\n")
    with pytest.raises(C.ConfigError) as e:
        C.load(p)
    msg = str(e.value)
    assert str(p) in msg and "methd" in msg and "[planes]" in msg and "method" in msg


def test_unknown_section_is_refused(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text("[plane]\nmethod = 'ransac'\n")
    with pytest.raises(C.ConfigError, match=r"unknown section \[plane\]"):
        C.load(p)


def test_a_key_outside_any_section_says_so_and_names_its_section(tmp_path):
    """`rate_hz = 5` at the top of config.toml (no [light] line above it) was refused as 'unknown
    section [rate_hz]'."""
    p = tmp_path / "c.toml"
    p.write_text("rate_hz = 5\n[light]\nenabled = true\n")
    with pytest.raises(C.ConfigError) as e:
        C.load(p)
    msg = str(e.value)
    assert "key 'rate_hz' = 5 is outside any section; put it under its [section] line (it is a key of [light])" in msg
    assert "unknown section" not in msg, msg


@pytest.mark.parametrize(
    "toml, expect",
    [
        ("[planes]\nredetect_every = 'often'\n", r"\[planes\] redetect_every: expected int >= 1, got str 'often'"),
        ("[render]\nshadow = 1\n", r"\[render\] shadow: expected bool, got int 1"),
        ("[planes]\nmethod = 'hough'\n", r"one of 'ransac', 'region', 'opencv'.*got str 'hough'"),
        ("[anchor]\npixel = [1, 2, 3]\n", r"\[anchor\] pixel: expected list of length 2"),
        ("[output]\nport = 80.5\n", r"\[output\] port: expected int in 0..65535, got float 80.5"),
    ],
)
def test_wrong_types_name_key_expected_and_value(tmp_path, toml, expect):
    p = tmp_path / "c.toml"
    p.write_text(toml)
    with pytest.raises(C.ConfigError, match=expect):
        C.load(p)


def test_int_accepted_for_float_and_overrides_apply():
    cfg = C.apply_overrides(C.defaults(), ["planes.smoothing=0", "source.url=replay://x", "anchor.pixel=[10, 20]"])
    assert cfg.planes.smoothing == 0.0 and isinstance(cfg.planes.smoothing, float)
    assert cfg.source.url == "replay://x"
    assert cfg.anchor.pixel == [10, 20]
    with pytest.raises(C.ConfigError, match="expected section.key=value"):
        C.apply_overrides(C.defaults(), ["nonsense"])


def test_missing_file_and_bad_toml(tmp_path):
    with pytest.raises(C.ConfigError, match="not found"):
        C.load(tmp_path / "nope.toml")
    p = tmp_path / "bad.toml"
    p.write_text("[planes\n")
    with pytest.raises(C.ConfigError, match="not valid TOML"):
        C.load(p)


@pytest.mark.parametrize(
    "toml, expect",
    [
        ("[source]\nmax_frames = " + "9" * 5000 + "\n", "an integer of over 4300 digits"),
        ("[anchor]\npixel = " + "[" * 5000 + "]" * 5000 + "\n", "nested too deep"),
    ],
    ids=["huge-int", "deep"],
)
def test_toml_that_python_cannot_hold_is_one_config_error(tmp_path, toml, expect):
    # valid TOML, but tomllib raised ValueError / RecursionError past the TOMLDecodeError handler
    p = tmp_path / "c.toml"
    p.write_text(toml)
    with pytest.raises(C.ConfigError, match=rf"c.toml: not valid TOML: .*{expect}"):
        C.load(p)
    value = toml.split(" = ", 1)[1].strip()
    section_key = "source.max_frames" if "max_frames" in toml else "anchor.pixel"
    with pytest.raises(C.ConfigError, match=rf"override {section_key}=.*\.\.\.: .*{expect}"):
        C.apply_overrides(C.defaults(), [f"{section_key}={value}"])


def test_a_config_larger_than_any_config_is_refused_not_read_whole(tmp_path):
    # a huge file given by mistake (an image, a log) was read whole before TOML refused it
    p = tmp_path / "big.toml"
    with open(p, "wb") as f:
        f.truncate(2 << 20)  # sparse: no disk space used
    with pytest.raises(C.ConfigError, match=r"big.toml: larger than 1 MiB, not a config file"):
        C.load(p)
    with pytest.raises(C.ConfigError, match=r"/dev/zero: not a regular file"):  # pipes and devices: refused first
        C.load("/dev/zero")


def test_an_implicit_config_toml_that_is_refused_says_it_was_read_because_it_is_here(tmp_path, monkeypatch, capsys):
    """Another tool's config.toml in the current folder stopped every command with 'config.toml:
    unknown section [server]', and nothing said that illuminet reads ./config.toml by itself."""
    from illuminet.cli import main

    (tmp_path / "config.toml").write_text("[server]\nport = 80\n")
    monkeypatch.chdir(tmp_path)
    assert main(["config"]) == 2
    err = capsys.readouterr().err
    assert "config.toml: unknown section [server]" in err, err
    assert "(./config.toml is read when no --config is given: correct it, pass --config FILE" in err, err
    assert main(["--config", "config.toml", "config"]) == 2  # named: the user knows which file it is
    assert "is read when no --config is given" not in capsys.readouterr().err


def test_illuminet_config_piped_into_head_ends_quietly():
    """`illuminet config | head` ended in a BrokenPipeError traceback once head had its lines: here the
    reader leaves before the first line."""
    import subprocess
    import sys

    p = subprocess.Popen(
        [sys.executable, "-m", "illuminet", "config"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=REPO
    )
    p.stdout.close()  # the reader is gone: every write of the command meets a broken pipe
    err = p.stderr.read().decode()
    assert p.wait(timeout=120) == 0, err
    assert "Traceback" not in err and "BrokenPipe" not in err, err
