"""`illuminet calibrate ...` end to end on files, and view capture from a Source."""

from __future__ import annotations

import json
import os
import re
import zlib

import cv2
import numpy as np
import pytest

from illuminet.calibration.board import BoardSpec
from illuminet.calibration.calibfile import (
    Calibration,
    CalibrationError,
    CameraCalib,
    StereoCalib,
    load_calibration,
)
from illuminet.calibration.capture import capture_views
from illuminet.calibration.charuco import detect
from illuminet.calibration.synthview import board_plane, board_poses, degrade, pixel_rays, render
from illuminet.cli import main
from illuminet.runtime.frame import Frame, Intrinsics
from illuminet.runtime.stage import Source

SPEC = BoardSpec(9, 6, 30.0, 22.0, "DICT_4X4_50")
CAM = CameraCalib(
    640, 400, np.array([[450.0, 0, 322.3], [0, 451.0, 197.6], [0, 0, 1]]), np.array([-0.12, 0.05, 0.0005, -0.0003, 0.0])
)


def _write_views(folder, n, seed=0):
    folder.mkdir(parents=True, exist_ok=True)
    plane = board_plane(SPEC)
    rays = pixel_rays(CAM.scaled_to(1280, 800))
    for k, (R, t) in enumerate(board_poses(SPEC, n, seed)):
        img, _ = render(CAM, R, t, [plane], background=128, rays=rays)
        cv2.imwrite(str(folder / f"view_{k:02d}.png"), degrade(img, 0.7, 2.0, k))


def test_board_png_and_pdf(tmp_path, capsys):
    png = tmp_path / "b.png"
    assert (
        main(
            [
                "calibrate",
                "board",
                "--squares",
                "9x6",
                "--square-mm",
                "30",
                "--marker-mm",
                "22",
                "--dictionary",
                "DICT_4X4_50",
                "--dpi",
                "100",
                "-o",
                str(png),
            ]
        )
        == 0
    )
    img = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
    sq = round(30 * 100 / 25.4)
    assert img.shape == (6 * sq, 9 * sq)
    assert b"pHYs" in png.read_bytes()[:100]
    # the printed board is the board we detect: every inner corner found
    padded = cv2.copyMakeBorder(img, 40, 40, 40, 40, cv2.BORDER_CONSTANT, value=255)
    assert len(detect(padded, SPEC)) == SPEC.n_corners
    side = json.loads((tmp_path / "b.json").read_text())
    assert BoardSpec.from_dict(side["board"]) == SPEC
    pdf = tmp_path / "b.pdf"
    assert main(["calibrate", "board", "-o", str(pdf), "--page", "a4"]) == 0
    data = pdf.read_bytes()
    assert data.startswith(b"%PDF-1.4") and data.rstrip().endswith(b"%%EOF")
    # image drawn at exactly 220 x 160 mm (11x8 squares of 20 mm): 623.62 x 453.54 pt
    m = re.search(rb"q ([\d.]+) 0 0 ([\d.]+) [\d.]+ [\d.]+ cm /Im0 Do Q", data)
    assert m and float(m.group(1)) == pytest.approx(220 / 25.4 * 72, abs=1e-3)
    assert float(m.group(2)) == pytest.approx(160 / 25.4 * 72, abs=1e-3)
    # a well-formed file: every xref offset points at its object, and the embedded image is the board
    xref_at = int(data[data.rindex(b"startxref") + 9 :].split()[0])
    rows = data[xref_at:].split(b"\n")[3 : 3 + 6]
    for k, row in enumerate(rows, start=1):
        off = int(row.split()[0])
        assert data[off:].startswith(f"{k} 0 obj".encode())
    im = re.search(rb"/Width (\d+) /Height (\d+) .*?/Length (\d+) >>\nstream\n", data, re.S)
    w, h, n = (int(g) for g in im.groups())
    pixels = np.frombuffer(zlib.decompress(data[im.end() : im.end() + n]), np.uint8).reshape(h, w)
    assert (
        len(detect(cv2.copyMakeBorder(pixels, 40, 40, 40, 40, cv2.BORDER_CONSTANT, value=255), BoardSpec()))
        == BoardSpec().n_corners
    )
    assert main(["calibrate", "board", "--square-mm", "40", "--marker-mm", "30", "-o", str(pdf)]) == 2
    assert "does not fit on a4" in capsys.readouterr().err


def test_intrinsics_cli_writes_calibration(tmp_path, capsys):
    _write_views(tmp_path / "views", 8)
    out = tmp_path / "cam.json"
    rc = main(
        [
            "calibrate",
            "intrinsics",
            str(tmp_path / "views"),
            "--squares",
            "9x6",
            "--square-mm",
            "30",
            "--marker-mm",
            "22",
            "--dictionary",
            "DICT_4X4_50",
            "-o",
            str(out),
        ]
    )
    assert rc == 0, capsys.readouterr().err
    c = load_calibration(out)
    assert abs(c.camera("left").K[0, 0] / 450.0 - 1) < 0.01
    assert c.meta["board"]["squares_x"] == 9


@pytest.mark.timeout(120)  # a pipe given as a file waited for a writer for ever
def test_cli_errors_are_one_line_exit_2(tmp_path, capsys):
    _write_views(tmp_path / "views", 2)
    args = ["--squares", "9x6", "--square-mm", "30", "--marker-mm", "22", "--dictionary", "DICT_4X4_50"]
    assert main(["calibrate", "intrinsics", str(tmp_path / "views"), *args]) == 2
    assert "too few views: 2 usable" in capsys.readouterr().err
    assert main(["calibrate", "intrinsics", str(tmp_path / "nothing"), *args]) == 2
    assert "no such image file or folder" in capsys.readouterr().err
    bad = tmp_path / "bad.json"
    bad.write_text("{}")
    assert main(["calibrate", "import-depthai", str(bad), "-o", str(tmp_path / "x.json")]) == 2
    assert "missing key 'cameraData'" in capsys.readouterr().err
    binary = tmp_path / "photo.json"
    binary.write_bytes(b"\x89PNG\r\n\x1a\n\xf1\xff")  # a picture saved under the wrong name
    assert main(["calibrate", "import-depthai", str(binary), "-o", str(tmp_path / "x.json")]) == 2
    err = capsys.readouterr().err
    assert "photo.json: not a text file" in err and len(err.strip().splitlines()) == 1
    os.mkfifo(tmp_path / "pipe.json")
    for argv in (
        ["calibrate", "import-depthai", str(tmp_path / "pipe.json"), "-o", str(tmp_path / "x.json")],
        ["calibrate", "board", "--board", str(tmp_path / "pipe.json"), "-o", str(tmp_path / "b.png")],
    ):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "pipe.json: not a regular file" in err and len(err.strip().splitlines()) == 1, err
    deep = tmp_path / "deep.json"
    deep.write_text('{"cameraData": ' + "[" * 100000 + "]" * 100000 + "}")  # was a RecursionError traceback
    assert main(["calibrate", "import-depthai", str(deep), "-o", str(tmp_path / "x.json")]) == 2
    err = capsys.readouterr().err
    assert "deep.json: JSON nested too deeply" in err and len(err.strip().splitlines()) == 1, err


def test_an_output_that_cannot_be_made_is_one_line(tmp_path, capsys):
    (tmp_path / "afile").write_text("not a folder")
    for argv in (
        ["calibrate", "board", "-o", str(tmp_path / "afile" / "board.pdf")],
        ["calibrate", "capture", "synthetic://indoor?frames=2", "-o", str(tmp_path / "afile" / "views")],
    ):
        assert main(argv) == 1
        err = capsys.readouterr().err
        assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
        assert str(tmp_path / "afile") in err and "folder you can write to" in err


def _depthai_data(translation_cm=-7.5):
    """A two-camera DepthAI export: socket 1 -> socket 2 at ``translation_cm`` along x."""
    K = [[800.0, 0, 640.0], [0, 800.0, 400.0], [0, 0, 1]]
    cam = {"width": 1280, "height": 800, "intrinsicMatrix": K, "distortionCoeff": [0.0] * 14, "cameraType": 0}
    data = {
        "cameraData": [
            [
                1,
                cam
                | {
                    "extrinsics": {
                        "rotationMatrix": np.eye(3).tolist(),
                        "toCameraSocket": 2,
                        "translation": {"x": translation_cm, "y": 0.0, "z": 0.0},
                    }
                },
            ],
            [
                2,
                cam
                | {
                    "extrinsics": {
                        "rotationMatrix": [[0.0] * 3] * 3,
                        "toCameraSocket": -1,
                        "translation": {"x": 0, "y": 0, "z": 0},
                    }
                },
            ],
        ],
        "stereoRectificationData": {"leftCameraSocket": 1, "rightCameraSocket": 2},
    }
    return data


def test_import_depthai_cli(tmp_path, capsys):
    src = tmp_path / "dai.json"
    src.write_text(json.dumps(_depthai_data()))
    out = tmp_path / "ours.json"
    assert main(["calibrate", "import-depthai", str(src), "-o", str(out)]) == 0
    c = load_calibration(out)
    assert c.stereo.baseline_m == pytest.approx(0.075) and c.stereo.T[0] == pytest.approx(-0.075)
    assert "baseline 75.00 mm" in capsys.readouterr().out


def _one_line(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    return err


def test_import_depthai_refuses_a_pair_without_baseline(tmp_path, capsys):
    src = tmp_path / "dai.json"
    src.write_text(json.dumps(_depthai_data()))
    out = tmp_path / "ours.json"
    argv = ["calibrate", "import-depthai", str(src), "-o", str(out)]
    assert main([*argv, "--left-socket", "1", "--right-socket", "1"]) == 2
    err = _one_line(capsys)
    assert "same socket 1" in err and "--left-socket" in err and "two different sockets" in err
    assert main([*argv, "--left-socket", "2"]) == 2  # the file's right socket is 2 too
    assert "same socket 2" in _one_line(capsys)
    src.write_text(json.dumps(_depthai_data(translation_cm=0.0)))  # two sockets at one place
    assert main(argv) == 2
    assert "0 mm baseline" in _one_line(capsys)
    assert not out.exists()  # nothing written that load_calibration would refuse later
    # one side given, and the file names no pair: it wrote a file with no stereo pair, without a word
    data = _depthai_data()
    del data["stereoRectificationData"]
    src.write_text(json.dumps(data))
    assert main([*argv, "--left-socket", "1"]) == 2
    err = _one_line(capsys)
    assert "--left-socket given" in err and "give --right-socket too" in err
    assert not out.exists()
    assert main(argv) == 0  # no pair asked for and none named: the cameras alone, as before


def _cam0(d):
    return d["cameraData"][0][1]


BAD_DEPTHAI = [  # each was a traceback, or a calibration written without a word (exit 0)
    (lambda d: d.update(stereoRectificationData=[1, 2]), "stereoRectificationData: expected an object"),
    (lambda d: d["stereoRectificationData"].update(leftCameraSocket=True), "leftCameraSocket: expected a camera"),
    (lambda d: _cam0(d).update(cameraType="abc"), "cameraData[0].cameraType: expected 0 (perspective) or 1"),
    (lambda d: _cam0(d).update(width="wide"), "cameraData[0].width: expected the image width in pixels"),
    (lambda d: _cam0(d).update(width=1280.7), "cameraData[0].width: expected the image width"),  # truncated
    (lambda d: _cam0(d).update(height=1e999), "cameraData[0].height: expected the image height"),
    (lambda d: _cam0(d).update(distortionCoeff="abc"), "cameraData[0].distortionCoeff: expected a list"),
    (lambda d: _cam0(d).update(distortionCoeff=[float("nan")] * 14), "distortionCoeff: expected finite numbers"),
    (
        lambda d: _cam0(d).update(intrinsicMatrix=[[800, 0, -9000], [0, 800, 400], [0, 0, 1]]),
        "principal point (-9000, 400) is outside the 1280x800 image",
    ),
    (
        lambda d: _cam0(d).update(intrinsicMatrix=[[800, 0, 640], [0, 800, 400], [5, 5, 5]]),
        "intrinsicMatrix: expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]",
    ),
    (lambda d: _cam0(d).update(extrinsics=[1, 2]), "cameraData[0].extrinsics: expected an object"),
    (lambda d: _cam0(d)["extrinsics"].update(toCameraSocket="two"), "toCameraSocket: expected a camera socket"),
    (
        lambda d: _cam0(d)["extrinsics"].update(translation={"x": "a", "y": 0, "z": 0}),
        "extrinsics.translation.x: expected a finite number of centimetres",
    ),
    (lambda d: _cam0(d)["extrinsics"].update(translation={"x": 1e300, "y": 0, "z": 0}), "translation.x: expected"),
    (lambda d: d["cameraData"][0].__setitem__(0, 10**9), "cameraData[0][0]: expected a camera socket number"),
    (lambda d: d["cameraData"][1].__setitem__(0, 1), "cameraData[1]: socket 1 appears twice"),
]


@pytest.mark.parametrize("edit,expect", BAD_DEPTHAI, ids=[e for _, e in BAD_DEPTHAI])
def test_import_depthai_refuses_malformed_entries_in_one_line(tmp_path, capsys, edit, expect):
    data = _depthai_data()
    edit(data)
    src, out = tmp_path / "dai.json", tmp_path / "ours.json"
    src.write_text(json.dumps(data))
    assert main(["calibrate", "import-depthai", str(src), "-o", str(out)]) == 2
    err = _one_line(capsys)
    assert f"{src}: " in err and expect in err, err
    assert not out.exists()


def test_board_keeps_a_json_it_did_not_write(tmp_path, capsys):
    cal = tmp_path / "calibration.json"
    cal.write_text('{"format": "illuminet-calibration", "cameras": {}}\n')
    before = cal.read_bytes()
    assert main(["calibrate", "board", "--dpi", "50", "-o", str(tmp_path / "calibration.png")]) == 2
    err = _one_line(capsys)
    assert str(cal) in err and "choose another -o name" in err
    assert cal.read_bytes() == before and not (tmp_path / "calibration.png").exists()
    # its own board description from an earlier run is replaced without fuss
    for mm in ("20", "25"):
        assert main(["calibrate", "board", "--dpi", "50", "--square-mm", mm, "-o", str(tmp_path / "b.png")]) == 0
    assert json.loads((tmp_path / "b.json").read_text())["board"]["square_mm"] == 25.0


@pytest.mark.parametrize(
    "text, message",
    [
        ('{"board": {"squares_x": "a"}}', "board.squares_x: expected a whole number of squares"),
        ("[1, 2]", "expected a JSON object with the board keys (squares_x, squares_y"),
        ('{"board": 5}', "expected a JSON object with the board keys"),
        ("{}", "no board keys; expected some of squares_x"),  # used to give the default board without a word
        ('{"board": {}}', "no board keys"),
        ('{"board": {"square_mn": 30}}', "unknown board key(s) 'square_mn'; expected only squares_x"),
        ('{"board": {"legacy": 1}}', "board.legacy: expected true or false, got int 1"),
        ('{"board": {"marker_mm": "x"}}', "board.marker_mm: expected a marker side in mm"),
        ('{"board": {"squares_x": 2}}', "board: expected at least 3x3 squares, got 2x8"),
        ('{"board": {"squares_x": 300, "dictionary": "DICT_ARUCO_ORIGINAL"}}', "has only 1024"),
        ("[" * 100_000, "cannot read board file"),
    ],
)
def test_a_bad_board_file_is_one_line(tmp_path, capsys, text, message):
    bd = tmp_path / "bd.json"
    bd.write_text(text)
    _write_views(tmp_path / "views", 1)
    for argv in (
        ["calibrate", "board", "--board", str(bd), "--dpi", "50", "-o", str(tmp_path / "b.png")],
        ["calibrate", "intrinsics", str(tmp_path / "views"), "--board", str(bd)],
    ):
        assert main(argv) == 2, argv
        err = _one_line(capsys)
        assert f"{bd}: " in err and message in err, err
    assert not (tmp_path / "b.png").exists()


@pytest.mark.parametrize(
    "make, says",
    [
        (lambda p: None, "no such file"),
        (lambda p: p.mkdir(), "it is a folder"),
        (lambda p: p.write_bytes(b"%PDF-1.4\n\xe2\xe3\xcf\xd3\n"), "not a text file"),  # the board's PDF
    ],
)
def test_a_board_file_that_is_missing_a_folder_or_the_pdf_says_what_to_pass(tmp_path, capsys, make, says):
    """`--board board.pdf` said "'utf-8' codec can't decode byte 0xe2 in position 10", a folder or a
    missing file a bare "[Errno 21] Is a directory"; none said what --board wants."""
    bd = tmp_path / "board.pdf"
    make(bd)
    _write_views(tmp_path / "views", 1)
    assert main(["calibrate", "intrinsics", str(tmp_path / "views"), "--board", str(bd)]) == 2
    err = _one_line(capsys)
    assert f"{bd}: cannot read board file: {says}; expected the board JSON that `illuminet calibrate board`" in err
    assert "Errno" not in err and "codec" not in err, err


def test_a_board_file_may_leave_keys_out_or_write_whole_numbers_as_floats(tmp_path, capsys):
    bd = tmp_path / "bd.json"
    bd.write_text('{"squares_x": 9.0, "squares_y": 6, "square_mm": 30, "marker_mm": 22, "dictionary": "DICT_4X4_50"}')
    assert main(["calibrate", "board", "--board", str(bd), "--dpi", "50", "-o", str(tmp_path / "b.png")]) == 0
    assert BoardSpec.from_dict(json.loads((tmp_path / "b.json").read_text())["board"]) == SPEC


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda d: d["cameras"]["left"].update(rms_px="abc"), "cameras.left.rms_px: expected"),
        (lambda d: d.update(meta=[1, 2]), "meta: expected an object"),
        (lambda d: d["stereo"].update(baseline_m="x"), "stereo.baseline_m: expected"),
    ],
)
def test_a_bad_calibration_file_given_to_a_command_is_one_line(tmp_path, capsys, mutate, message):
    _write_views(tmp_path / "views", 1)
    d = Calibration(
        {"left": CAM, "right": CAM}, StereoCalib("left", "right", np.eye(3), np.array([-0.075, 0, 0]))
    ).to_dict()
    mutate(d)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(d))
    board = ["--squares", "9x6", "--square-mm", "30", "--marker-mm", "22", "--dictionary", "DICT_4X4_50"]
    views = str(tmp_path / "views")
    for argv in (
        ["calibrate", "intrinsics", views, *board, "--guess", str(bad)],
        ["calibrate", "stereo", views, views, *board, "--intrinsics", str(bad), "-o", str(tmp_path / "s.json")],
    ):
        assert main(argv) == 2, argv
        err = _one_line(capsys)
        assert f"{bad}: " in err and message in err and "correct it in the file" in err, err
    assert not (tmp_path / "s.json").exists()


@pytest.mark.parametrize("sub", ["board", "capture", "intrinsics", "stereo", "photometric", "import-depthai"])
def test_calibrate_subcommands_show_the_global_options(sub, capsys):
    with pytest.raises(SystemExit):
        main(["calibrate", sub, "--help"])
    out = capsys.readouterr().out
    assert "global options (also accepted before the command)" in out
    assert "--log-level" in out and "--set" in out and "--config" in out


def test_global_options_after_a_calibrate_subcommand(tmp_path, capsys):
    out = str(tmp_path / "b.png")
    for opts in (["--log-level", "debug"], ["--set", "light.rate_hz=5"], ["-c", str(tmp_path / "none.toml")]):
        rc = main(["calibrate", "board", *opts, "--dpi", "50", "-o", out])
        err = capsys.readouterr().err
        assert "unrecognized arguments" not in err, err
        if opts[0] == "-c":  # read, not ignored: the missing file is reported
            assert rc == 2 and "none.toml" in err, err
        else:
            assert rc == 0, err
    # they take effect: an unknown key is a configuration error, not silently dropped
    assert main(["calibrate", "board", "--set", "nosuch.key=5", "--dpi", "50", "-o", out]) == 2
    assert "unknown section [nosuch]" in _one_line(capsys)


def test_board_picture_size_is_bounded(tmp_path, capsys):
    out = str(tmp_path / "x.png")
    assert main(["calibrate", "board", "--square-mm", "10000", "--marker-mm", "9000", "-o", out]) == 2
    err = _one_line(capsys)
    assert "Mpx" in err and "--dpi" in err and "--square-mm" in err
    for argv in (["--dpi", "100000"], ["--dpi", "nan"], ["--dpi", "inf"], ["--square-mm", "inf"]):
        assert main(["calibrate", "board", *argv, "-o", out]) == 2, argv
        err = _one_line(capsys)
        assert "--dpi" in err or "square size" in err, err
    assert not (tmp_path / "x.png").exists()


def _bracket_dir(folder):
    """A static random scene at 5..80 ms, 80x60 PNGs named by exposure."""
    folder.mkdir()
    rad = np.random.default_rng(0).uniform(0.02, 1.0, (60, 80, 3))
    for ms in (5, 10, 20, 40, 80):
        code = np.clip(rad * ms / 40.0, 0, 1) ** (1 / 2.2) * 255
        cv2.imwrite(str(folder / f"img_{ms}ms.png"), code.astype(np.uint8))
    return folder


@pytest.mark.timeout(60)  # --smoothness nan used to hang in OpenCV
def test_photometric_flags_are_checked(tmp_path, capsys):
    br = _bracket_dir(tmp_path / "br")
    out = tmp_path / "r.npy"
    cmd = ["calibrate", "photometric", str(br), "-o", str(out)]
    for value in ("-1", "0", "inf", "nan"):
        assert main([*cmd, "--smoothness", value]) == 2, value
        assert "--smoothness: expected" in _one_line(capsys)
    for value in ("0", "-5", "100000"):
        assert main([*cmd, "--samples", value]) == 2, value
        assert "--samples: expected 1..1000" in _one_line(capsys)
    times = tmp_path / "t.json"
    for value in ('"abc"', "null", "[1]", "true", "-0.01", "NaN"):
        times.write_text(f'{{"img_5ms.png": {value}, "img_10ms.png": 0.01}}')
        assert main([*cmd, "--times", str(times)]) == 2, value
        err = _one_line(capsys)
        assert f'{times}: "img_5ms.png": expected the exposure time in seconds' in err, err
    os.mkfifo(tmp_path / "pipe.json")  # waited for a writer for ever
    assert main([*cmd, "--times", str(tmp_path / "pipe.json")]) == 2
    assert "pipe.json: not a regular file" in _one_line(capsys)
    times.write_text("[" * 100000 + "]" * 100000)  # was a RecursionError traceback
    assert main([*cmd, "--times", str(times)]) == 2
    assert f"{times}: JSON nested too deeply" in _one_line(capsys)
    assert not out.exists()
    assert main([*cmd, "--samples", "60", "--smoothness", "20"]) == 0, capsys.readouterr().err
    assert np.load(out).shape == (256, 3)


def test_capture_refuses_a_folder_with_earlier_views(tmp_path, capsys):
    views = tmp_path / "views"
    views.mkdir()
    for k in range(3):  # an earlier capture
        (views / f"view_{k:03d}.png").write_bytes(b"earlier %d" % k)
    argv = ["calibrate", "capture", "synthetic://indoor?frames=2", "-o", str(views)]
    assert main(argv) == 2
    err = _one_line(capsys)
    assert f"{views}: output folder is not empty" in err and "choose a new folder" in err
    assert sorted(p.read_bytes() for p in views.iterdir()) == [b"earlier 0", b"earlier 1", b"earlier 2"]
    # the library refuses it too, before reading a frame
    src = _BoardSource(board_poses(SPEC, 2, seed=9))
    with pytest.raises(CalibrationError, match="output folder is not empty"):
        capture_views(src, views, SPEC)
    assert src._i == 0 and (views / "view_000.png").read_bytes() == b"earlier 0"
    # a failed sbs capture leaves only empty left/ and right/: trying again there is fine
    (tmp_path / "sbs" / "left").mkdir(parents=True)
    (tmp_path / "sbs" / "right").mkdir()
    with pytest.raises(CalibrationError, match=r"no usable board view in 0 frame\(s\)"):
        capture_views(_BoardSource([]), tmp_path / "sbs", SPEC, split="sbs")


def test_capture_flags_are_checked(tmp_path, capsys):
    out = tmp_path / "views"
    for flag, value in (
        ("--max-frames", "0"),
        ("--views", "0"),
        ("--coverage", "2"),
        ("--coverage", "nan"),
        ("--coverage", "-0.5"),
        ("--min-novelty", "nan"),
    ):
        assert main(["calibrate", "capture", "synthetic://indoor?frames=2", flag, value, "-o", str(out)]) == 2
        err = _one_line(capsys)
        assert err.startswith(f"illuminet calibrate capture: {flag}: expected") and value in err, err
    assert not out.exists()


class _BoardSource(Source):
    """A real Source: yields frames of the board at given poses (each pose twice: a still board)."""

    def __init__(self, poses):
        self._poses = [p for p in poses for _ in range(2)]
        self._plane = board_plane(SPEC)
        self._rays = pixel_rays(CAM.scaled_to(1280, 800))
        self._i = 0

    def read(self):
        if self._i >= len(self._poses):
            return None
        R, t = self._poses[self._i]
        img, _ = render(CAM, R, t, [self._plane], background=128, rays=self._rays)
        bgr = degrade(img, 0.7, 2.0, self._i)
        self._i += 1
        return Frame(
            self._i,
            self._i * 33_000_000,
            self._i * 33_000_000,
            cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB),
            None,
            Intrinsics(450, 451, 322.3, 197.6, 640, 400),
        )


def test_capture_keeps_diverse_views(tmp_path):
    poses = board_poses(SPEC, 6, seed=9)
    seen = []
    with _BoardSource(poses) as src:
        res = capture_views(src, tmp_path / "cap", SPEC, views=50, on_frame=lambda n, v, s: seen.append(v))
    assert res.frames_read == 12
    kept = [v for v in seen if v.accepted]
    assert 4 <= len(kept) <= 6  # the repeated frame of each pose is never kept twice
    assert any("too similar" in v.reason for v in seen)
    assert len(res.files) == len(kept) and all(f.is_file() for f in res.files)
    assert (tmp_path / "cap" / "coverage.png").is_file()
    assert 0 < res.coverage <= 1 and set(res.coverage_text) <= {"#", ".", "\n"}


def test_capture_without_board_fails_clearly(tmp_path):
    class Blank(Source):
        n = 0

        def read(self):
            self.n += 1
            if self.n > 3:
                return None
            return Frame(
                self.n,
                self.n,
                self.n,
                np.full((400, 640, 3), 100, np.uint8),
                None,
                Intrinsics(450, 451, 320, 200, 640, 400),
            )

    with pytest.raises(CalibrationError, match=r"no usable board view in 3 frame\(s\)"):
        capture_views(Blank(), tmp_path / "cap", SPEC)


def test_capture_cli_from_replay_then_intrinsics(tmp_path, capsys):
    """End to end: a recorded session of a board -> `calibrate capture replay://...` -> `calibrate intrinsics`."""
    from illuminet.runtime.stream.session import SessionWriter

    session = tmp_path / "session"
    src = _BoardSource(board_poses(SPEC, 10, seed=21))
    with SessionWriter(session, source="test://board", fsync=False) as w:
        while (f := src.read()) is not None:
            w.append(f.replace(depth=np.zeros(f.color.shape[:2], np.float32)))
    views = tmp_path / "views"
    args = ["--squares", "9x6", "--square-mm", "30", "--marker-mm", "22", "--dictionary", "DICT_4X4_50"]
    rc = main(["calibrate", "capture", f"replay://{session}?timing=asap", *args, "-o", str(views), "--views", "50"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert "coverage" in out.out and (views / "coverage.png").is_file()
    kept = sorted(views.glob("view_*.png"))
    assert 6 <= len(kept) <= 10
    rc = main(["calibrate", "intrinsics", str(views), *args, "-o", str(tmp_path / "cam.json")])
    assert rc == 0, capsys.readouterr().err
    assert abs(load_calibration(tmp_path / "cam.json").camera("left").K[0, 0] / 450.0 - 1) < 0.01


class _SbsBoardSource(Source):
    """Side-by-side stereo frames (left|right) of the board: a UVC stereo camera's format."""

    R = cv2.Rodrigues(np.array([0.002, -0.01, 0.003]))[0]
    T = np.array([-0.06, 0.0004, 0.001])

    def __init__(self, poses):
        self._poses = poses
        self._plane = board_plane(SPEC)
        self._rays = pixel_rays(CAM.scaled_to(1280, 800))
        self._i = 0

    def read(self):
        if self._i >= len(self._poses):
            return None
        Rb, tb = self._poses[self._i]
        left, _ = render(CAM, Rb, tb, [self._plane], background=128, rays=self._rays)
        right, _ = render(CAM, self.R @ Rb, self.R @ tb + self.T, [self._plane], background=128, rays=self._rays)
        sbs = degrade(np.hstack([left, right]), 0.7, 2.0, self._i)
        self._i += 1
        return Frame(
            self._i,
            self._i,
            self._i,
            cv2.cvtColor(sbs, cv2.COLOR_BGR2RGB),
            None,
            Intrinsics(450, 451, 322.3, 197.6, 1280, 400),
        )


def test_sbs_capture_then_stereo_cli(tmp_path, capsys):
    poses = board_poses(SPEC, 12, seed=31, distance=(0.45, 0.7), shift=(0.06, 0.05))
    res = capture_views(_SbsBoardSource(poses), tmp_path / "cap", SPEC, views=50, split="sbs", min_novelty=0.03)
    left = sorted((tmp_path / "cap" / "left").glob("*.png"))
    right = sorted((tmp_path / "cap" / "right").glob("*.png"))
    assert len(left) == len(right) >= 8 and [p.name for p in left] == [p.name for p in right]
    assert len(res.files) == 2 * len(left)
    out = tmp_path / "rig.json"
    rc = main(
        [
            "calibrate",
            "stereo",
            str(tmp_path / "cap" / "left"),
            str(tmp_path / "cap" / "right"),
            "--squares",
            "9x6",
            "--square-mm",
            "30",
            "--marker-mm",
            "22",
            "--dictionary",
            "DICT_4X4_50",
            "-o",
            str(out),
        ]
    )
    assert rc == 0, capsys.readouterr().err
    c = load_calibration(out)
    assert abs(c.stereo.baseline_m / np.linalg.norm(_SbsBoardSource.T) - 1) < 0.01
    assert c.stereo.rectification is not None and c.color_camera == "left"


def test_board_page_is_checked_for_a_png_too(tmp_path, capsys):
    """`calibrate board -o x.png --page A0x` wrote the PNG, exit 0: only the PDF writer looked at --page."""
    png = tmp_path / "x.png"
    assert main(["calibrate", "board", "-o", str(png), "--page", "A0x"]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and "--page 'A0x': expected one of a4, a3" in err[0], err
    assert not png.exists()
    assert main(["calibrate", "board", "-o", str(png), "--page", "a3"]) == 0  # a valid page: a note, not a refusal
    assert "--page applies to a PDF only" in capsys.readouterr().out and png.exists()
