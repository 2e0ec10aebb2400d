"""``illuminet doctor``: every check reports, essentials decide the exit code, bad IMU URLs are named."""

from __future__ import annotations

import json

from illuminet import cli
from illuminet.commands.doctor import MISSING, NONE, OK, Check, exit_code, run_checks

NAMES = ["OpenGL (EGL)", "onnxruntime", "OpenCV", "PyAV (H.264 video)", "DepthAI (OAK)", "V4L2 cameras", "serial ports"]


def test_report_lists_every_check_with_status(capsys):
    rc = cli.main(["doctor"])
    out = capsys.readouterr().out
    for name in NAMES:
        assert f"] {name}: " in out
    assert "essentials: " in out
    checks = run_checks()
    gl = checks[0]
    # exit code follows the essentials; on a machine without EGL the GL line says how to fix it
    assert rc == exit_code(checks)
    if gl.status == OK:
        assert "OpenGL" in gl.detail
    else:
        assert "libegl1" in gl.fix
    ort = checks[1]
    assert ort.status == OK and "CPUExecutionProvider" in ort.detail


def test_json_output(capsys):
    cli.main(["doctor", "--json"])
    data = json.loads(capsys.readouterr().out)
    assert [d["name"] for d in data] == NAMES
    assert all(d["status"] in (OK, MISSING, NONE) for d in data)
    dai = data[4]
    assert data[3]["status"] in (OK, MISSING)
    assert dai["status"] in (OK, NONE) and dai["detail"].startswith("3.")  # DepthAI v3
    if dai["status"] == NONE:
        assert "udev" in dai["fix"]


def test_configured_imu_port_that_cannot_open_is_reported(capsys):
    rc = cli.main(["--set", "imu.url='/dev/ttyNOPE9'", "doctor"])
    out = capsys.readouterr().out
    assert "[MISSING] serial ports" in out and "/dev/ttyNOPE9" in out and "dialout" in out
    assert rc == exit_code(run_checks())  # an optional device does not fail the doctor


def test_loop_imu_url_opens():
    serial_check = run_checks("loop://")[6]
    assert "(opens)" in serial_check.detail


def test_exit_code_follows_essentials_only():
    ok = Check("OpenGL (EGL)", OK, "", essential=True)
    assert exit_code([ok, Check("DepthAI (OAK)", NONE, ""), Check("V4L2 cameras", MISSING, "")]) == 0
    assert exit_code([ok, Check("onnxruntime", MISSING, "", essential=True)]) == 1


def test_a_broken_config_is_a_finding_not_a_refusal(tmp_path, capsys):
    """With a config.toml that does not parse, `doctor` refused to run at all: the one tool a user
    reaches for when something is wrong. It now reports the file as a failed essential and checks the
    machine with the built-in defaults."""
    bad = tmp_path / "bad.toml"
    bad.write_text("[light\nx = 1\n")
    rc = cli.main(["--config", str(bad), "doctor"])
    out = capsys.readouterr().out
    assert rc == 1 and f"[MISSING] configuration: not loaded: {bad}: not valid TOML" in out, out
    for name in NAMES:
        assert f"] {name}: " in out  # every other check still ran
    assert cli.main(["--config", str(bad), "config"]) == 2  # other commands still refuse it
