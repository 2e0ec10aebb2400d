"""Serial IMU protocol over pySerial's loop://: garbage, checksum errors, resync, matching to frames."""

from __future__ import annotations

import time

import numpy as np
import pytest
import serial

from illuminet.hw.serial_imu import (
    ImuMatcher,
    ImuProtocolError,
    ImuStage,
    LineParser,
    SerialImu,
    _OffsetClock,
    checksum,
    format_line,
    list_ports,
    parse_line,
    parse_serial_url,
    rotation_from_list,
    write_samples,
)
from illuminet.runtime.config import apply_overrides, defaults
from illuminet.runtime.frame import Frame, ImuSample, Intrinsics

G = 9.80665


def _frame(t_host_ns: int, gravity=None) -> Frame:
    return Frame(
        seq=0,
        t_device_ns=t_host_ns,
        t_host_ns=t_host_ns,
        color=np.zeros((4, 4, 3), np.uint8),
        depth=None,
        intrinsics=Intrinsics(4, 4, 2, 2, 4, 4),
        gravity=gravity,
    )


def test_line_round_trip_and_checksum():
    line = format_line(123456789, (0.1, -0.2, 9.81), (0.01, 0.02, -0.03))
    assert line.startswith(b"$IMU,123456789,") and line.endswith(b"\r\n")
    payload, cs = line[1:].split(b"*")
    assert int(cs[:2], 16) == checksum(payload)
    s = parse_line(line)
    assert s.t_ns == 123456789
    assert s.accel == pytest.approx((0.1, -0.2, 9.81)) and s.gyro == pytest.approx((0.01, 0.02, -0.03))
    s2 = parse_line(format_line(5, (0, 0, 1)))
    assert s2.gyro is None
    # NMEA checksums are case-insensitive hex; a bare \n ending is fine
    assert parse_line(line.replace(cs[:2], cs[:2].lower()).rstrip(b"\r\n") + b"\n").t_ns == 123456789


@pytest.mark.parametrize(
    "bad, why",
    [
        (b"IMU,1,0,0,9*00", "start with '\\$'"),
        (b"$IMU,1,0,0,9", "no '\\*XX' checksum"),
        (b"$IMU,1,0,0,9*ZZ", "not two hex digits"),
        (b"$GGA,1,0,0,9*" + f"{checksum(b'GGA,1,0,0,9'):02X}".encode(), "unknown sentence"),
        (b"$IMU,1,0,0*" + f"{checksum(b'IMU,1,0,0'):02X}".encode(), "expected 4 fields"),
        (b"$IMU,1,0,x,9*" + f"{checksum(b'IMU,1,0,x,9'):02X}".encode(), "not a number"),
        (b"$IMU,1,0,nan,9*" + f"{checksum(b'IMU,1,0,nan,9'):02X}".encode(), "non-finite"),
    ],
)
def test_bad_lines_say_what_is_wrong(bad, why):
    with pytest.raises(ImuProtocolError, match=why):
        parse_line(bad)


def test_checksum_mismatch_is_named():
    line = bytearray(format_line(1, (0, 0, 9.8)))
    line[6] = ord("7")  # corrupt a digit of the timestamp, keep the old checksum
    with pytest.raises(ImuProtocolError, match="checksum mismatch"):
        parse_line(bytes(line))


def test_parser_resyncs_after_garbage_cut_lines_and_split_reads():
    good = [format_line(i * 1000, (0.0, 0.0, G)) for i in range(6)]
    bad_cs = bytearray(good[2])
    bad_cs[-4] = ord("0") if bad_cs[-4] != ord("0") else ord("1")  # break the checksum digits
    stream = (
        b"\x00\xff noise before the first line\r\n"
        + good[0]
        + good[1][:12]  # a line cut off mid-way (sender reset): no newline
        + bytes(bad_cs)
        + b"$"
        + b"A" * 400
        + b"\r\n"  # overlong junk
        + good[3]
        + b"garbage\n"
        + good[4]
        + good[5]
    )
    p = LineParser()
    got = []
    for i in range(0, len(stream), 7):  # arrives in small, arbitrary pieces
        got += p.feed(stream[i : i + 7])
    assert [s.t_ns for s in got] == [0, 3000, 4000, 5000]
    c = p.counters()
    assert c["good"] == 4 and c["bad_checksum"] == 1
    assert c["malformed"] >= 1 and c["overlong"] >= 1 and c["garbage_bytes"] > 0


def test_loop_url_reader_end_to_end_with_errors():
    """A real pySerial loop:// port: writer and background reader on the same port."""
    port = serial.serial_for_url("loop://", timeout=0.05)
    matcher = ImuMatcher(max_skew_ms=5.0, tau_s=0.0)
    t0 = time.monotonic_ns()
    samples = [ImuSample(t0 + i * 2_000_000, (0.0, 0.0, G), (0.0, 0.0, 0.1)) for i in range(300)]
    with SerialImu("loop://", matcher=matcher, clock="host", port=port) as imu:
        write_samples(port, samples[:100])  # > 4096 bytes in total: written in chunks
        port.write(b"\x13\x37garbage$IMU,broken\r\n")
        bad = bytearray(format_line(samples[100].t_ns, samples[100].accel))
        bad[-4] = ord("0") if bad[-4] != ord("0") else ord("1")
        port.write(bytes(bad))  # checksum error: skipped, counted
        write_samples(port, samples[101:])
        deadline = time.time() + 5
        while imu.parser.good < 299 and time.time() < deadline:
            time.sleep(0.01)
        st = imu.stats()
    port.close()
    assert st["good"] == 299 and st["bad_checksum"] == 1 and st["malformed"] >= 1 and st["garbage_bytes"] >= 9
    s, g = matcher.match(samples[150].t_ns + 1_000_000)
    assert s and g is not None
    np.testing.assert_allclose(g, [0, 0, -1], atol=1e-6)  # accel +z up -> gravity -z
    _, g = matcher.match(samples[100].t_ns)  # the corrupted sample's neighbours still match
    assert g is not None


def test_matcher_nearest_within_skew_rotation_and_lowpass():
    # IMU mounted with its z axis along the camera's -y (camera y points down): rotation maps z -> -y
    R = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]
    m = ImuMatcher(max_skew_ms=10.0, rotation=R, tau_s=0.2)
    t = 1_000_000_000
    for i in range(200):  # level and still, with a shake in x from sample 100 on (motion, not gravity)
        shake = 3.0 * np.sin(i) if i >= 100 else 0.0
        m.add(ImuSample(t + i * 5_000_000, (shake, 0.0, G)))
    samples, g = m.match(t + 99 * 5_000_000 + 1_000_000)
    assert samples and all(abs(s.t_ns - (t + 99 * 5_000_000 + 1_000_000)) <= 10_000_000 for s in samples)
    np.testing.assert_allclose(g, [0, 1, 0], atol=1e-6)  # gravity points down = camera +y
    assert samples[0].accel == pytest.approx((0.0, -G, 0.0))  # samples are given in camera axes
    # during the shake the low-pass keeps gravity close to down (raw accel swings by up to 17 degrees)
    _, g2 = m.match(t + 199 * 5_000_000)
    assert np.degrees(np.arccos(np.clip(g2 @ [0, 1, 0], -1, 1))) < 6
    # too far from any sample: no data rather than a stale gravity
    assert m.match(t + 199 * 5_000_000 + 50_000_000) == ((), None)
    f = m.attach(_frame(t + 50 * 5_000_000))
    assert f.gravity is not None and len(f.imu) >= 1
    assert m.attach(_frame(t + 10**12)).gravity is None
    keep = np.array([0, 0, 1], np.float32)
    assert m.attach(_frame(t + 50 * 5_000_000, gravity=keep)).gravity is keep  # device gravity wins


def test_matcher_refuses_bad_rotation_and_drops_out_of_order():
    with pytest.raises(ValueError, match="not a rotation"):
        rotation_from_list([1, 0, 0, 0, 1, 0, 0, 0, -1])  # a reflection
    with pytest.raises(ValueError, match="9 numbers"):
        rotation_from_list([1, 0, 0])
    m = ImuMatcher()
    m.add(ImuSample(10, (0, 0, 1)))
    m.add(ImuSample(5, (0, 0, 1)))
    assert m.out_of_order == 1


def test_offset_clock_uses_minimum_delay():
    c = _OffsetClock(window_s=10)
    # sender clock starts at 0, host at 1e12; delays 3, 1, 5 ms: the 1 ms one sets the offset
    dev = [0, 10_000_000, 20_000_000]
    arrival = [10**12 + 3_000_000, 10**12 + 11_000_000, 10**12 + 25_000_000]
    out = [c.to_host(d, a) for d, a in zip(dev, arrival)]
    assert out[2] == 10**12 + 20_000_000 + 1_000_000


def test_serial_url_parsing():
    assert parse_serial_url("serial:///dev/ttyUSB0?baud=921600") == ("/dev/ttyUSB0", 921600)
    assert parse_serial_url("serial://loop://", 9600) == ("loop://", 9600)
    assert parse_serial_url("loop://?logging=debug&baud=57600") == ("loop://?logging=debug", 57600)
    with pytest.raises(ValueError, match="baud must be an integer"):
        parse_serial_url("serial:///dev/ttyUSB0?baud=fast")
    with pytest.raises(ValueError, match="empty"):
        parse_serial_url("")


def test_missing_port_error_names_it():
    with pytest.raises(OSError, match="/dev/does-not-exist"):
        SerialImu("serial:///dev/does-not-exist").open()


def test_stage_from_config_over_loop():
    assert ImuStage.from_config(defaults()) is None
    cfg = apply_overrides(defaults(), [("imu", "url", "serial://loop://?baud=230400"), ("imu", "clock", "host")])
    stage = ImuStage.from_config(cfg)
    assert stage.reader.baudrate == 230400 and stage.reader.url == "loop://"
    with stage:
        port = stage.reader._port
        t0 = time.monotonic_ns()
        write_samples(port, [ImuSample(t0 + i * 1_000_000, (0.0, -G, 0.0)) for i in range(20)])
        deadline = time.time() + 5
        while stage.reader.parser.good < 20 and time.time() < deadline:
            time.sleep(0.01)
        f = stage.process(_frame(t0 + 10_000_000))
    np.testing.assert_allclose(f.gravity, [0, 1, 0], atol=1e-6)
    assert stage.stats()["good"] == 20


def test_list_ports_returns_dicts():
    for p in list_ports():
        assert set(p) == {"device", "description", "hwid"}


# ------------------------------------------- issue 13, class 4: plausible-looking garbage is not trusted


def _line(t_ns: int, accel, gyro=None) -> bytes:
    return format_line(t_ns, accel, gyro)


def _raw(payload: bytes) -> bytes:
    return b"$" + payload + b"*" + f"{checksum(payload):02X}".encode() + b"\r\n"


@pytest.mark.parametrize(
    "payload, why",
    [
        (b"IMU,1000,0,0,1e308", "acceleration .* is not physical"),
        (b"IMU,1000,0,0,314", "acceleration .* is not physical"),  # 32 g
        (b"IMU,1000,0,0,9.8,0,0,1e6", "angular rate .* is not physical"),
        (b"IMU,1000,0,0,1e999", "non-finite"),
        (b"IMU,18446744073709551616,0,0,9.8", "not an integer number of nanoseconds"),  # 2**64: 20 digits
        (b"IMU,9999999999999999999,0,0,9.8", "beyond 2\\*\\*63-1"),
        (b"IMU,-5,0,0,9.8", "not an integer number of nanoseconds"),
        (b"IMU,1_000,0,0,9.8", "not an integer number of nanoseconds"),
        (b"IMU,1000,0,0, 9.8", "not a number"),
    ],
)
def test_implausible_values_with_a_valid_checksum_are_refused(payload, why):
    with pytest.raises(ImuProtocolError, match=why):
        parse_line(_raw(payload))
    p = LineParser()
    assert p.feed(_line(1, (0, 0, G)) + _raw(payload) + _line(2, (0, 0, G))) != []
    assert p.good == 2 and p.implausible + p.malformed == 1


def _reader(clock: str = "device") -> SerialImu:
    # the reader's line handling without a port: _accept(sample, arrival) is what its thread calls
    return SerialImu("loop://", matcher=ImuMatcher(max_skew_ms=10.0, tau_s=0.3), clock=clock)


def test_one_huge_acceleration_line_does_not_zero_gravity():
    """|a| = 1e308 with a valid checksum used to hold the low-passed gravity at zero for ~100 s."""
    imu = _reader()
    host0 = 10**12
    stream = b"".join(_line(i * 5_000_000, (0.0, 0.0, G)) for i in range(50))
    stream += _raw(b"IMU,250000000,0,0,1e308") + _raw(b"IMU,250000001,1e300,0,0")
    stream += b"".join(_line(i * 5_000_000, (0.0, 0.0, G)) for i in range(51, 100))
    for k, s in enumerate(imu.parser.feed(stream)):
        imu._accept(s, host0 + s.t_ns + 1_000_000 + k)
    _, g = imu.matcher.match(host0 + 60 * 5_000_000)
    np.testing.assert_allclose(g, [0, 0, -1], atol=1e-6)
    st = imu.stats()
    assert st["implausible"] == 2 and st["good"] == 99


def test_a_far_future_timestamp_does_not_disable_the_imu():
    """One line stamped far in the future used to make every later line 'out of order' for good."""
    for clock in ("device", "host"):
        imu = _reader(clock)
        host0 = 10**12
        t0 = host0 if clock == "host" else 0
        for i in range(100):
            t = t0 + i * 5_000_000
            arrival = host0 + i * 5_000_000 + 1_000_000
            if i == 40:
                imu._accept(ImuSample(t + 10**18, (0.0, 0.0, G)), arrival)  # ~31 years ahead
            imu._accept(ImuSample(t, (0.0, 0.0, G)), arrival)
        st = imu.stats()
        assert st["time_rejected"] == 1 and st["out_of_order"] == 0, (clock, st)
        samples, g = imu.matcher.match(host0 + 99 * 5_000_000 + 1_000_000)
        assert samples and g is not None, clock
        np.testing.assert_allclose(g, [0, 0, -1], atol=1e-6)


def test_a_sender_clock_restart_is_followed_after_agreeing_lines():
    from illuminet.hw.serial_imu import RESYNC_LINES

    imu = _reader("device")
    host0 = 10**12
    for i in range(50):  # sender clock at 1000 s, then the board resets to 0
        imu._accept(ImuSample(10**12 + i * 5_000_000, (0.0, 0.0, G)), host0 + i * 5_000_000)
    n = RESYNC_LINES + 400  # 2 s after the restart: the gravity low-pass (tau 0.3 s) has settled
    for j in range(n):  # ... and the board is now held on its side
        imu._accept(ImuSample(j * 5_000_000, (0.0, G, 0.0)), host0 + (50 + j) * 5_000_000)
    st = imu.stats()
    assert st["clock_resyncs"] == 1 and st["time_rejected"] == RESYNC_LINES - 1
    _, g = imu.matcher.match(host0 + (50 + n - 1) * 5_000_000)
    np.testing.assert_allclose(g, [0, -1, 0], atol=1e-2)  # the new timeline's samples are used


def test_a_first_line_far_in_the_future_is_outlived():
    # nothing to compare the very first line with: it is accepted, and the real timeline takes over
    imu = _reader("device")
    host0 = 10**12
    imu._accept(ImuSample(2**62, (0.0, 0.0, G)), host0)
    for i in range(1, 80):
        imu._accept(ImuSample(i * 5_000_000, (0.0, 0.0, G)), host0 + i * 5_000_000)
    assert imu.stats()["clock_resyncs"] == 1
    samples, g = imu.matcher.match(host0 + 79 * 5_000_000)
    assert samples and g is not None


def test_matcher_refuses_implausible_samples_and_outlives_a_future_one():
    from illuminet.hw.serial_imu import RESYNC_LINES

    m = ImuMatcher(max_skew_ms=10.0, tau_s=0.3)
    t = 1_000_000_000
    for i in range(10):
        m.add(ImuSample(t + i * 5_000_000, (0.0, 0.0, G)))
    m.add(ImuSample(t + 10 * 5_000_000, (0.0, 0.0, 1e308)))
    m.add(ImuSample(t + 11 * 5_000_000, (float("nan"), 0.0, G)))
    assert m.implausible == 2
    np.testing.assert_allclose(m.match(t + 9 * 5_000_000)[1], [0, 0, -1], atol=1e-6)
    m.add(ImuSample(t + 10**18, (0.0, 0.0, G)))  # reached the matcher by another path (an OAK's IMU)
    for i in range(12, 12 + RESYNC_LINES + 5):
        m.add(ImuSample(t + i * 5_000_000, (0.0, 0.0, G)))
    assert m.timeline_resets == 1
    assert m.match(t + (12 + RESYNC_LINES + 4) * 5_000_000)[1] is not None


def test_loop_port_with_hostile_lines_keeps_gravity():
    """End to end over loop://: a 1e308 line and a far-future line among good ones, host clock."""
    port = serial.serial_for_url("loop://", timeout=0.05)
    matcher = ImuMatcher(max_skew_ms=10.0, tau_s=0.3)
    with SerialImu("loop://", matcher=matcher, clock="host", port=port) as imu:
        t0 = time.monotonic_ns() - 10**9  # stamped in the last second, as a host-clock sender does
        good = [ImuSample(t0 + i * 5_000_000, (0.0, 0.0, G)) for i in range(100)]
        write_samples(port, good[:50])
        port.write(_raw(f"IMU,{good[50].t_ns - 1},0,0,1e308".encode()))
        port.write(_line(t0 + 10**18, (0.0, 0.0, G)))
        write_samples(port, good[50:])
        deadline = time.time() + 5
        while imu.parser.good + imu.parser.implausible < 102 and time.time() < deadline:
            time.sleep(0.01)
        time.sleep(0.05)
        st = imu.stats()
    port.close()
    assert st["implausible"] == 1 and st["time_rejected"] == 1 and st["out_of_order"] == 0, st
    _, g = matcher.match(good[99].t_ns)
    np.testing.assert_allclose(g, [0, 0, -1], atol=1e-6)
