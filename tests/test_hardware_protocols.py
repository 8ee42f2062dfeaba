"""Byte-level tests of the servo protocols, the tracker lines and manual entry.

Expected bytes are written out from the published formats (Pololu Maestro user's guide,
"Serial Servo Commands"; Lynxmotion SSC-32 manual), not computed by the code under test.
"""

from __future__ import annotations

import os
import threading
import time
import tty

import numpy as np
import pytest
import serial

from bayesrob.hardware import maestro as mae
from bayesrob.hardware import ssc32
from bayesrob.hardware.controller import HardwareError, LimitError, SerialLink
from bayesrob.hardware.simdevice import (
    PROTOCOL_ERROR_BIT,
    MaestroDecoder,
    SSC32Decoder,
    parse_ssc32,
)
from bayesrob.hardware.tracker import (
    ManualTracker,
    StreamTracker,
    TrackerLineError,
    checksum,
    format_plain,
    format_pxyt,
    number_layout,
    parse_line,
    parse_manual,
    reject_outliers,
)

H = bytes.fromhex


# ------------------------------------------------------------------------------ Maestro


@pytest.mark.parametrize(("built", "expected"), [
    # Set Target channel 2 to 1500 us = 6000 quarter-us = 0x1770: low 7 bits 0x70, high 0x2E.
    (mae.set_target(2, 6000), "84 02 70 2E"),
    (mae.set_target(2, 6000, "pololu"), "AA 0C 04 02 70 2E"),
    (mae.set_target(0, 0), "84 00 00 00"),  # 0 = pulses off
    (mae.set_target(5, 16383, "pololu", device=1), "AA 01 04 05 7F 7F"),
    # Set Speed 140 = 0x8C -> 0x0C, 0x01.
    (mae.set_speed(0, 140), "87 00 0C 01"),
    (mae.set_speed(0, 140, "pololu"), "AA 0C 07 00 0C 01"),
    (mae.set_acceleration(1, 4), "89 01 04 00"),
    (mae.set_acceleration(1, 255, "pololu"), "AA 0C 09 01 7F 01"),
    (mae.get_position(2), "90 02"),
    (mae.get_position(2, "pololu"), "AA 0C 10 02"),
    (mae.get_moving_state(), "93"),
    (mae.get_moving_state("pololu"), "AA 0C 13"),
    (mae.get_errors(), "A1"),
    (mae.get_errors("pololu", device=7), "AA 07 21"),
    (mae.go_home(), "A2"),
    (mae.go_home("pololu"), "AA 0C 22"),
])
def test_maestro_commands_match_the_published_bytes(built: bytes, expected: str) -> None:
    assert isinstance(built, bytes)
    assert built == H(expected)


def test_maestro_values_and_replies() -> None:
    assert mae.quarter_us(1500) == 6000
    assert mae.quarter_us(1250.25) == 5001
    assert mae.decode_u16(H("70 17")) == 6000  # low byte first, full 8-bit bytes
    assert mae.decode_u16(H("00 01")) == 256
    assert mae.decode_errors(0x0011) == ["serial signal error", "serial protocol error"]
    assert mae.speed_units(500.0) == 20  # 20 * 0.25 us per 10 ms = 500 us/s
    with pytest.raises(ValueError, match="two-byte"):
        mae.decode_u16(b"\x01")
    with pytest.raises(ValueError, match="target"):
        mae.set_target(0, 16384)
    with pytest.raises(ValueError, match="channel"):
        mae.set_target(24, 6000)
    with pytest.raises(ValueError, match="device number"):
        mae.get_errors("pololu", device=128)
    with pytest.raises(ValueError, match="protocol"):
        mae.get_errors("ascii")  # type: ignore[arg-type]


def test_maestro_decoder_reads_both_protocols_byte_by_byte() -> None:
    stream = (mae.set_target(2, 6000) + mae.set_target(3, 5001, "pololu")
              + mae.get_position(3, "pololu", device=9)  # another device on the line: ignored
              + mae.set_speed(1, 140) + mae.get_moving_state("pololu") + mae.get_errors()
              + mae.go_home())
    dec = MaestroDecoder(device=12)
    got = []
    for b in stream:
        got += dec.feed(bytes([b]))
    assert got == [(0x84, H("02 70 2E")), (0x84, H("03 09 27")), (0x87, H("01 0C 01")),
                   (0x93, b""), (0xA1, b""), (0xA2, b"")]
    assert dec.errors == 0


def test_maestro_decoder_baud_rate_indication_byte() -> None:
    # Alone before a compact command it is consumed silently ...
    dec = MaestroDecoder()
    dec.baud_byte = True
    assert dec.feed(H("AA") + mae.get_errors()) == [(0xA1, b"")]
    assert dec.errors == 0
    # ... and as a Pololu command's first byte it is that command's start too.
    dec = MaestroDecoder()
    dec.baud_byte = True
    assert dec.feed(mae.get_errors("pololu")) == [(0xA1, b"")]
    assert dec.errors == 0
    # A Maestro not detecting a baud rate takes a lone 0xAA for a command cut short.
    dec = MaestroDecoder()
    assert dec.feed(H("AA") + mae.get_errors()) == [(0xA1, b"")]
    assert dec.errors & PROTOCOL_ERROR_BIT


def test_maestro_models() -> None:
    assert [mae.n_channels(m) for m in ("micro", "mini12", "mini18", "mini24", "mini")] == \
        [6, 12, 18, 24, 24]
    assert mae.n_channels(None) == 24
    with pytest.raises(ValueError, match="unknown Maestro model 'nano'"):
        mae.n_channels("nano")


def test_maestro_decoder_resynchronises_after_garbage() -> None:
    dec = MaestroDecoder()
    # A stray data byte, then a Set Target cut short by a new command byte.
    got = dec.feed(H("05") + H("84 02 70") + mae.get_moving_state() + mae.set_target(1, 6000))
    assert got == [(0x93, b""), (0x84, H("01 70 2E"))]
    assert dec.errors & PROTOCOL_ERROR_BIT


# ------------------------------------------------------------------------------ SSC-32


def test_ssc32_commands_match_the_published_format() -> None:
    assert ssc32.move_command([(0, 1500)]) == b"#0P1500\r"
    assert ssc32.move_command([(0, 1500), (1, 1600)], 500, 1000) == \
        b"#0P1500S500#1P1600S500T1000\r"  # a group move: one T at the end
    assert ssc32.move_command([(31, 2500), (4, 500)], time_ms=0) == b"#31P2500#4P500T0\r"
    assert ssc32.query_movement() == b"Q\r"
    assert ssc32.query_pulse(5) == b"QP5\r"
    assert ssc32.version() == b"VER\r"
    with pytest.raises(ValueError, match="500..2500"):
        ssc32.move_command([(0, 2501)])
    with pytest.raises(ValueError, match="channel"):
        ssc32.move_command([(32, 1500)])


def test_ssc32_decoder_and_parser() -> None:
    dec = SSC32Decoder()
    lines = []
    for b in b"#0P1500S500#1P1600S500T1000\rQ\rQP0\rVER\r#0 P1500 T200\rQP1QP2\rbogus\r":
        lines += dec.feed(bytes([b]))
    parsed = [parse_ssc32(line) for line in lines]
    assert parsed == [("move", [(0, 1500, 500), (1, 1600, 500)], 1000), ("Q",), ("QP", [0]),
                      ("VER",), ("move", [(0, 1500, None)], 200), ("QP", [1, 2]), None]


# ------------------------------------------------------------------------------ controller bytes


@pytest.fixture
def raw_pty():
    """A pseudo-terminal: the test holds the device end, the code under test opens the port."""
    master, slave = os.openpty()
    tty.setraw(slave)
    port = serial.Serial(os.ttyname(slave), 115200, timeout=0.2, exclusive=True)
    yield master, SerialLink(port, "servo")
    port.close()
    os.close(master)
    os.close(slave)


def _read_all(fd: int, wait: float = 0.1) -> bytes:
    time.sleep(wait)
    os.set_blocking(fd, False)
    try:
        return os.read(fd, 4096)
    except BlockingIOError:
        return b""


LIMITS = {"a": ((900.0, 2100.0), (900.0, 2100.0))}


def test_maestro_move_writes_set_targets_for_the_arm_channels(raw_pty) -> None:
    master, link = raw_pty
    ctl = mae.Maestro(link, {"a": (2, 3)}, LIMITS, protocol="compact")
    ctl.move({"a": (1500, 1250.25)})
    assert _read_all(master) == H("84 02 70 2E 84 03 09 27")
    ctl = mae.Maestro(link, {"a": (2, 3)}, LIMITS, protocol="pololu", device=12)
    ctl.move({"a": (1500, 1250.25)})
    assert _read_all(master) == H("AA 0C 04 02 70 2E AA 0C 04 03 09 27")


def test_maestro_auto_baud_sends_0xaa_alone_first_with_the_compact_protocol(raw_pty) -> None:
    master, link = raw_pty

    def answer_get_errors() -> None:
        # Protocol error flagged: what a Maestro not detecting a baud rate makes of the lone AA.
        time.sleep(0.05)
        os.write(master, H("10 00"))

    for protocol, first in (("compact", H("AA A1")), ("pololu", H("AA 0C 21"))):
        ctl = mae.Maestro(link, {"a": (0, 1)}, LIMITS, protocol=protocol, auto_baud=True,
                          speed_us_per_s=None)
        t = threading.Thread(target=answer_get_errors)
        t.start()
        description = ctl.connect()
        t.join()
        # The Pololu protocol needs no extra byte: its first command starts with 0xAA.
        assert _read_all(master) == first
        if protocol == "compact":
            assert "protocol error" not in description  # ours, from the lone 0xAA
        else:
            assert "cleared earlier errors: serial protocol error" in description


def test_maestro_refuses_channels_its_model_lacks(raw_pty) -> None:
    master, link = raw_pty
    with pytest.raises(ValueError, match=r"channel 6 of arm 'a' does not exist \(a Micro "
                                         r"Maestro 6 has channels 0..5\)"):
        mae.Maestro(link, {"a": (5, 6)}, LIMITS, model="micro")
    mae.Maestro(link, {"a": (5, 6)}, LIMITS, model="mini12")
    assert _read_all(master) == b""


def test_settle_timeout_follows_the_distance_and_the_speed(raw_pty) -> None:
    _, link = raw_pty
    ctl = mae.Maestro(link, {"a": (0, 1)}, LIMITS, speed_us_per_s=500.0, retries=1)
    first = ctl.settle_timeout_s({"a": (1500.0, 1500.0)})  # no target known: a full span
    ctl._targets.update({0: 1500.0, 1: 1500.0})
    near = ctl.settle_timeout_s({"a": (1550.0, 1500.0)})
    far = ctl.settle_timeout_s({"a": (1500.0, 2100.0)})
    slack = near - 2 * 50 / 500
    assert far - slack == pytest.approx(2 * 600 / 500)
    assert first - slack == pytest.approx(2 * 1200 / 500)  # limits 900..2100
    ctl.speed_us_per_s = 1000.0
    assert ctl.settle_timeout_s({"a": (1500.0, 2100.0)}) - slack == pytest.approx(1.2)


def test_ssc32_move_is_one_group_command(raw_pty) -> None:
    master, link = raw_pty
    ctl = ssc32.SSC32(link, {"a": (0, 1)}, LIMITS, speed_us_per_s=750)
    ctl.move({"a": (1500, 1234)})
    assert _read_all(master) == b"#0P1500S750#1P1234S750\r"


@pytest.mark.parametrize("protocol", ["maestro", "ssc32"])
@pytest.mark.parametrize("bad", [(2100.25, 1500.0), (1500.0, 899.0), (float("nan"), 1500.0),
                                 (1500.0, float("inf"))])
def test_out_of_limit_move_sends_nothing(raw_pty, protocol: str, bad) -> None:
    master, link = raw_pty
    cls = mae.Maestro if protocol == "maestro" else ssc32.SSC32
    ctl = cls(link, {"a": (0, 1), "b": (2, 3)}, {**LIMITS, "b": LIMITS["a"]})
    with pytest.raises(LimitError, match="nothing was sent"):
        # The good arm comes first: checking must finish before any byte of the move goes out.
        ctl.move({"b": (1500.0, 1500.0), "a": bad})
    with pytest.raises(LimitError):
        ctl.move_and_settle({"a": bad})
    assert _read_all(master) == b""


def test_ssc32_rejects_limits_wider_than_its_range(raw_pty) -> None:
    master, link = raw_pty
    ctl = ssc32.SSC32(link, {"a": (0, 1)}, {"a": ((400.0, 2600.0), (400.0, 2600.0))})
    with pytest.raises(LimitError, match="SSC-32's range"):
        ctl.move({"a": (450.0, 1500.0)})
    with pytest.raises(LimitError, match="no channels"):
        ctl.move({"z": (1500.0, 1500.0)})
    assert _read_all(master) == b""


def test_query_retries_a_lost_reply_and_fails_clearly_without_one(raw_pty) -> None:
    master, link = raw_pty
    ctl = mae.Maestro(link, {"a": (0, 1)}, LIMITS, retries=3, sleep=lambda s: None)

    def answer_second_request() -> None:
        requests = 0
        deadline = time.monotonic() + 2
        while requests < 2 and time.monotonic() < deadline:
            data = _read_all(master, 0.01)
            requests += data.count(mae.GET_POSITION)
            if requests == 2:
                os.write(master, H("70 17"))

    t = threading.Thread(target=answer_second_request)
    t.start()
    assert ctl.channel_position(0) == 1500.0
    t.join()
    assert ctl.failed_queries == 1
    with pytest.raises(HardwareError, match=r"Get Moving State got 0 of 1 reply bytes.*3 tries"):
        ctl.is_moving()


def test_short_and_invalid_replies_are_errors(raw_pty) -> None:
    master, link = raw_pty
    ctl = ssc32.SSC32(link, {"a": (0, 1)}, LIMITS, retries=2, sleep=lambda s: None)
    stop = threading.Event()

    def reply_garbage() -> None:
        while not stop.is_set():
            if _read_all(master, 0.01):
                os.write(master, b"?")

    t = threading.Thread(target=reply_garbage)
    t.start()
    try:
        with pytest.raises(HardwareError, match="invalid reply 3f"):
            ctl.is_moving()
    finally:
        stop.set()
        t.join()


# ------------------------------------------------------------------------------ tracker lines


def test_checksum_is_the_nmea_xor() -> None:
    # The textbook NMEA sentence $GPGLL,5057.970,N,00146.110,E,142451,A*27.
    assert checksum("GPGLL,5057.970,N,00146.110,E,142451,A") == 0x27
    assert format_pxyt(1.0, -2.5) == b"$PXYT,1.000,-2.500*" + \
        f"{checksum('PXYT,1.000,-2.500'):02X}".encode() + b"\r\n"


def test_parse_tracker_lines() -> None:
    assert parse_line(format_pxyt(123.456, 78.9)) == (123.456, 78.9)
    assert parse_line(b"$PXYT,10.5,20.25*" + f"{checksum('PXYT,10.5,20.25'):02x}".encode()
                      + b"\r\n") == (10.5, 20.25)
    assert parse_line(format_plain(1.5, 2.0), "plain") == (1.5, 2.0)
    good = format_pxyt(12.0, 34.0)
    flipped = good.replace(b"12.0", b"13.0")
    with pytest.raises(TrackerLineError) as err:
        parse_line(flipped)
    assert err.value.kind == "checksum"
    for bad in (b"PXYT,1,2*00\r\n", b"$PXYT,1,2\r\n", b"$PXYT,1,2*ZZ\r\n",
                b"$PXYT,1*" + f"{checksum('PXYT,1'):02X}".encode(),
                b"$GPXX,1,2*" + f"{checksum('GPXX,1,2'):02X}".encode(),
                b"$PXYT,nan,2*" + f"{checksum('PXYT,nan,2'):02X}".encode(), b"\xff\xfe\r\n"):
        with pytest.raises(TrackerLineError) as err:
            parse_line(bad)
        assert err.value.kind == "malformed", bad
    for bad in (b"1.5\r\n", b"a,b\r\n", b"1,2,3\r\n", b"inf,2\r\n"):
        with pytest.raises(TrackerLineError):
            parse_line(bad, "plain")


def _while_streaming(master: int, script: bytes, call):
    """call() while the device side writes script a moment after it started listening."""
    def stream() -> None:
        time.sleep(0.1)
        os.write(master, script)

    t = threading.Thread(target=stream)
    t.start()
    try:
        return call()
    finally:
        t.join()


def test_stream_tracker_drops_the_partial_line_and_rejects_bad_checksums(raw_pty) -> None:
    master, link = raw_pty
    tracker = StreamTracker(link, "pxyt", samples=5, timeout_s=2.0)
    bad = format_pxyt(500.0, 500.0)[:-4] + b"00\r\n"
    script = (b"T,999.000,999.000*00\r\n"  # the tail of a line sent before we listened
              + format_pxyt(10.0, 20.0) + bad + format_pxyt(11.0, 21.0) + b"$PXYT,oops\r\n"
              + format_pxyt(12.0, 19.0) + format_pxyt(100.0, 20.5) + format_pxyt(9.0, 20.0)
              + format_pxyt(13.0, 22.0))

    samples = _while_streaming(master, script, tracker.read_samples)
    assert samples.tolist() == [[10, 20], [11, 21], [12, 19], [100, 20.5], [9, 20]]
    assert (tracker.bad_checksum, tracker.malformed) == (1, 1)
    assert np.median(samples, axis=0).tolist() == [11.0, 20.0]  # the wild 100 does not count


def test_stream_tracker_refuses_a_line_that_lost_two_equal_bytes(raw_pty) -> None:
    """Two equal bytes lost from one line leave its XOR checksum valid: 256.044 arrives as
    256.0, a reading 44 um off that the outlier rule cannot see when readings agree. A line
    printed unlike the rest of the stream is refused and counted as malformed."""
    master, link = raw_pty
    tracker = StreamTracker(link, "pxyt", samples=5, timeout_s=2.0)
    whole = format_pxyt(256.044, 285.253)
    lost = whole.replace(b"44", b"", 1)
    assert lost != whole and parse_line(lost) == (256.0, 285.253)  # the checksum holds
    script = b"\r\n" + whole * 2 + lost + whole * 3

    d = _while_streaming(master, script, tracker.measure)
    assert d.tolist() == pytest.approx([256.044, 285.253], abs=1e-9)
    assert tracker.malformed == 1 and tracker.readings == 5
    assert number_layout(whole) == (3, 3) and number_layout(lost) == (1, 3)


def test_stream_tracker_takes_every_line_of_a_stream_without_a_fixed_layout(raw_pty) -> None:
    """A tracker printing %g (decimals as the value needs) has no layout to hold lines to."""
    master, link = raw_pty
    tracker = StreamTracker(link, "plain", samples=6, timeout_s=2.0)
    values = [(10.5, 20.25), (10.25, 20.5), (10.0, 20.0), (10.125, 20.125), (10.5, 20.0),
              (10.25, 20.25)]
    script = b"\r\n" + b"".join(f"{x:g},{y:g}\r\n".encode() for x, y in values)

    samples = _while_streaming(master, script, tracker.read_samples)
    assert samples.tolist() == [list(v) for v in values]
    assert tracker.malformed == 0


def test_reject_outliers_uses_a_robust_scale_with_a_floor() -> None:
    rng = np.random.default_rng(0)
    truth = np.array([120.0, 250.0])
    good = truth + rng.normal(0.0, 0.02, (9, 2))
    wild = np.vstack([good, truth + [6.0, -3.0]])
    kept, n = reject_outliers(wild)
    assert n == 1 and kept.tolist() == good.tolist()
    # With the outlier gone the mean is as close as 9 readings of sd 0.02 allow (4 sd of the
    # mean: 0.027 mm); the outlier alone would pull it 0.67 mm away.
    assert np.linalg.norm(kept.mean(axis=0) - truth) < 4 * 0.02 / 3
    assert np.linalg.norm(wild.mean(axis=0) - truth) > 0.6
    # Readings that agree to the last digit reject nothing, nor does one a hair away: the
    # floor (0.05 mm sd) stands in for a median distance of zero.
    same = np.tile(truth, (5, 1))
    assert reject_outliers(same)[1] == 0
    assert reject_outliers(np.vstack([same, truth + [0.001, 0.0]]))[1] == 0
    assert reject_outliers(np.vstack([same, truth + [0.2, 0.0]]))[1] == 1  # 4 floors away
    assert reject_outliers(np.vstack([same, truth + [0.2, 0.0]]), floor_mm=0.1)[1] == 0
    # At least half the readings always stay, however wild the rest.
    for seed in range(20):
        r = np.random.default_rng(seed).standard_cauchy((7, 2))
        assert len(reject_outliers(r)[0]) >= 4
    with pytest.raises(ValueError, match="shape"):
        reject_outliers(np.zeros((3, 3)))


def test_stream_tracker_measure_rejects_counts_and_averages(raw_pty) -> None:
    master, link = raw_pty
    tracker = StreamTracker(link, "pxyt", samples=5, timeout_s=2.0)
    script = (b"\r\n" + format_pxyt(10.0, 20.0) + format_pxyt(10.02, 20.0)
              + format_pxyt(60.0, 20.0)  # a reflection, with a good checksum
              + format_pxyt(9.98, 20.04) + format_pxyt(10.0, 19.96))

    d = _while_streaming(master, script, tracker.measure)
    assert tracker.outliers == 1 and tracker.readings == 5
    assert d.tolist() == pytest.approx([10.0, 20.0])  # the mean of the four good readings


def test_stream_tracker_times_out_clearly(raw_pty) -> None:
    master, link = raw_pty
    tracker = StreamTracker(link, "pxyt", samples=3, timeout_s=0.3)
    os.write(master, format_pxyt(1, 2)[:-4] + b"00\r\n")
    with pytest.raises(HardwareError, match="0 of 3 good readings"):
        tracker.measure()


# ------------------------------------------------------------------------------ manual entry


@pytest.mark.parametrize(("text", "expected"), [
    ("1 2", (1.0, 2.0)), ("  123.5   -4e1 ", (123.5, -40.0)), ("7,8", (7.0, 8.0)),
    ("7, 8", (7.0, 8.0))])
def test_parse_manual_accepts(text: str, expected) -> None:
    assert parse_manual(text) == expected


@pytest.mark.parametrize("text", ["", "1", "1 2 3", "a b", "nan 1", "1 inf", "1;2"])
def test_parse_manual_rejects(text: str) -> None:
    with pytest.raises(ValueError):
        parse_manual(text)


def test_manual_tracker_asks_again_until_valid_and_stops_on_eof() -> None:
    answers = iter(["", "12", "x y", "nan 3", "101.5 202.25", "3 4"])
    said: list[str] = []
    prompts: list[str] = []

    def read(prompt: str) -> str:
        prompts.append(prompt)
        return next(answers)

    tracker = ManualTracker(read, said.append)
    assert tracker.measure("[1/2] top train").tolist() == [101.5, 202.25]
    assert tracker.rejected == 4 and len(said) == 4
    assert all("not recorded" in s for s in said)
    assert prompts[0].startswith("[1/2] top train")
    assert tracker.measure().tolist() == [3.0, 4.0]

    def eof(prompt: str) -> str:
        raise EOFError

    with pytest.raises(HardwareError, match="input ended"):
        ManualTracker(eof, said.append).measure()
