#!/usr/bin/env python3
"""End-to-end test: the real firmware ELF running in psscan-avr-sim.

Talks to the firmware over the harness's pseudo-terminal exactly like a host
would (raw, 115200 8N1, no pyserial needed) and checks the answers and the
pin log. Run via `make test-sim`, or:

    python3 sim/test_sim.py --sim build/psscan-avr-sim --firmware build/psscan_led.elf \
        [--hang-firmware build/psscan_led_testhang.elf]
"""
import argparse
import os
import re
import select
import signal
import subprocess
import sys
import tempfile
import termios
import threading
import time
import tty

IDENT = "psscan-led fw=1.0.0 proto=1 leds=10"
LINE_RE = re.compile(r"^sim_us=(\d+) wall_us=(\d+) led=(\d) level=([01])$")


class Sim:
    """One harness instance plus an open pty."""

    def __init__(self, sim_bin, firmware, workdir, name):
        self.pin_log = os.path.join(workdir, f"{name}.pins")
        self.stderr_path = os.path.join(workdir, f"{name}.stderr")
        self.stderr = open(self.stderr_path, "w")
        self.t0 = time.monotonic()
        self.proc = subprocess.Popen(
            [sim_bin, "--firmware", firmware, "--pin-log", self.pin_log],
            stdout=subprocess.PIPE, stderr=self.stderr)
        line = self._read_stdout_line(5.0)
        m = re.fullmatch(r"PTY (/dev/pts/\d+)\n", line)
        assert m, f"bad first stdout line: {line!r}"
        self.pty_path = m.group(1)
        self.fd = None
        self.buf = b""
        self.open()

    def _read_stdout_line(self, timeout):
        fd = self.proc.stdout.fileno()
        data = b""
        deadline = time.monotonic() + timeout
        while not data.endswith(b"\n"):
            left = deadline - time.monotonic()
            assert left > 0, "harness printed no PTY line"
            r, _, _ = select.select([fd], [], [], left)
            if r:
                chunk = os.read(fd, 1)
                assert chunk, "harness stdout closed before the PTY line"
                data += chunk
        return data.decode()

    def open(self):
        self.fd = os.open(self.pty_path, os.O_RDWR | os.O_NOCTTY)
        # TCSANOW, not setraw's default TCSAFLUSH: the firmware may already have sent its
        # READY banner (the harness keeps the port raw from the start), and a flush would
        # drop its first bytes.
        tty.setraw(self.fd, termios.TCSANOW)
        attrs = termios.tcgetattr(self.fd)
        attrs[4] = attrs[5] = termios.B115200
        termios.tcsetattr(self.fd, termios.TCSANOW, attrs)
        self.buf = b""

    def close_port(self):
        os.close(self.fd)
        self.fd = None

    def write(self, data):
        os.write(self.fd, data)

    def read_line(self, timeout=2.0):
        deadline = time.monotonic() + timeout
        while b"\n" not in self.buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"timeout waiting for a line, have {self.buf!r}")
            r, _, _ = select.select([self.fd], [], [], left)
            if r:
                self.buf += os.read(self.fd, 4096)
        line, self.buf = self.buf.split(b"\n", 1)
        return line.decode("ascii")

    def no_more_output(self, wait=0.3):
        time.sleep(wait)
        r, _, _ = select.select([self.fd], [], [], 0)
        if r:
            self.buf += os.read(self.fd, 4096)
        assert self.buf == b"", f"unexpected extra output {self.buf!r}"

    def cmd(self, text, timeout=2.0):
        self.write(text.encode() + b"\n")
        return self.read_line(timeout)

    def pins(self):
        """[(sim_us, wall_us, led, level)] from the pin log, comments skipped."""
        out = []
        with open(self.pin_log) as f:
            for raw in f:
                if not raw.endswith("\n") or raw.startswith("#"):
                    continue
                m = LINE_RE.match(raw.rstrip("\n"))
                assert m, f"bad pin log line {raw!r}"
                out.append(tuple(int(g) for g in m.groups()))
        return out

    def levels(self):
        lv = [None] * 10
        for _, _, led, level in self.pins():
            lv[led] = level
        return lv

    def stop(self):
        if self.fd is not None:
            os.close(self.fd)
        self.proc.send_signal(signal.SIGTERM)
        rc = self.proc.wait(5)
        self.stderr.close()
        return rc


def expect(got, want):
    assert got == want, f"expected {want!r}, got {got!r}"


def on_only(levels, n):
    want = [0] * 10
    if n is not None:
        want[n] = 1
    assert levels == want, f"pin levels {levels}, expected only {n} on"


def test_basic(s, report):
    expect(s.read_line(3.0), "READY " + IDENT)
    header = open(s.pin_log).readline()
    assert header.startswith("# psscan-avr-sim pinlog v1 "), header
    on_only(s.levels(), None)

    expect(s.cmd("ID"), "OK ID " + IDENT)
    expect(s.cmd("PING"), "OK PONG")

    t = time.monotonic()
    expect(s.cmd("ON 3"), "OK ON 3")
    report["ON round trip ms"] = round((time.monotonic() - t) * 1000, 2)
    on_only(s.levels(), 3)  # pin already high when the answer arrives

    n_before = len(s.pins())
    expect(s.cmd("ON 7"), "OK ON 7")
    new = [(led, lvl) for _, _, led, lvl in s.pins()[n_before:]]
    expect(new, [(3, 0), (7, 1)])  # old off strictly before new on

    expect(s.cmd("STATE"), "OK STATE 7 timeout=3000 tripped=0")
    expect(s.cmd("OFF"), "OK OFF")
    on_only(s.levels(), None)
    expect(s.cmd("STATE"), "OK STATE OFF timeout=3000 tripped=0")


def test_errors(s):
    expect(s.cmd("ON 5"), "OK ON 5")
    pins_before = len(s.pins())
    cases = [
        (b"\n", "ERR 1 unknown command"),
        (b"\r\n", "ERR 1 unknown command"),
        (b"on 3\n", "ERR 1 unknown command"),
        (b"FOO\n", "ERR 1 unknown command"),
        (b"ON\n", "ERR 2 bad argument"),
        (b"ON x\n", "ERR 2 bad argument"),
        (b"ON  3\n", "ERR 2 bad argument"),
        (b"OFF 1\n", "ERR 2 bad argument"),
        (b"ON 10\n", "ERR 4 out of range"),
        (b"TIMEOUT 99\n", "ERR 4 out of range"),
        (b"TIMEOUT 60001\n", "ERR 4 out of range"),
        (b"\x00\xff\x80garbage\x01\x1b[A\n", "ERR 5 bad character"),
        (b"ON 2\x00\n", "ERR 5 bad character"),
        (b"X" * 33 + b"\n", "ERR 3 line too long"),
        (b"ON 1" + b"\xff" * 500 + b"\n", "ERR 3 line too long"),
    ]
    for data, want in cases:
        s.write(data)
        expect(s.read_line(), want)
    # 500 bytes of overlong garbage: exactly one answer, then back in sync.
    s.write(bytes((i * 37 + 11) % 256 for i in range(500)).replace(b"\n", b"x") + b"\n")
    expect(s.read_line(), "ERR 3 line too long")
    s.no_more_output()
    expect(s.cmd("PING\r"), "OK PONG")
    expect(s.cmd("STATE"), "OK STATE 5 timeout=3000 tripped=0")
    assert len(s.pins()) == pins_before, "a rejected line changed a pin"
    # Exactly 32 characters is still a line (leading zeros allowed).
    expect(s.cmd("TIMEOUT " + "0" * 20 + "3000"), "OK TIMEOUT 3000")
    expect(s.cmd("OFF"), "OK OFF")


def test_timeout(s, report):
    expect(s.cmd("TIMEOUT 500"), "OK TIMEOUT 500")
    expect(s.cmd("ON 2"), "OK ON 2")
    t_on = time.monotonic()
    on_pins = s.pins()[-1]
    expect(on_pins[2:], (2, 1))
    time.sleep(1.0)  # host silence
    off = [p for p in s.pins() if p[2] == 2 and p[3] == 0 and p[0] > on_pins[0]]
    assert off, "LED 2 did not switch off by itself"
    sim_ms = (off[0][0] - on_pins[0]) / 1000
    wall_ms = (off[0][1] - on_pins[1]) / 1000
    report["silence trip after ON (sim ms)"] = sim_ms
    report["silence trip after ON (harness wall ms)"] = wall_ms
    assert 500 <= sim_ms <= 520, sim_ms
    assert 495 <= wall_ms <= 560, wall_ms
    on_only(s.levels(), None)
    s.no_more_output(0.0)  # no unsolicited message
    expect(s.cmd("STATE"), "OK STATE OFF timeout=500 tripped=1")
    report["host wall s from ON to STATE"] = round(time.monotonic() - t_on, 3)
    expect(s.cmd("PING"), "OK PONG")  # keepalive does not clear tripped
    expect(s.cmd("STATE"), "OK STATE OFF timeout=500 tripped=1")

    # Keepalive: PING every 200 ms keeps the LED on past the timeout.
    expect(s.cmd("ON 4"), "OK ON 4")
    n = len(s.pins())
    for _ in range(8):
        time.sleep(0.2)
        expect(s.cmd("PING"), "OK PONG")
    assert len(s.pins()) == n, "LED changed despite keepalive"
    expect(s.cmd("STATE"), "OK STATE 4 timeout=500 tripped=0")
    expect(s.cmd("TIMEOUT 3000"), "OK TIMEOUT 3000")
    expect(s.cmd("OFF"), "OK OFF")


def test_reopen(s):
    s.close_port()
    time.sleep(0.1)
    s.open()
    expect(s.cmd("ID"), "OK ID " + IDENT)


def test_realtime(s, report):
    """Simulated vs wall time over a 2 s span, measured on the host."""
    s.cmd("ON 9")
    a = s.pins()[-1]
    ta = time.monotonic()
    time.sleep(2.0)
    s.cmd("ON 8")
    tb = time.monotonic()
    b = [p for p in s.pins() if p[2] == 8 and p[3] == 1][-1]
    sim_s = (b[0] - a[0]) / 1e6
    wall_s = (b[1] - a[1]) / 1e6
    host_s = tb - ta
    report["realtime: sim s / harness wall s / host s"] = (round(sim_s, 4), round(wall_s, 4), round(host_s, 4))
    lead = max(p[0] - p[1] for p in s.pins())
    report["max sim ahead of wall over log (us)"] = lead
    assert abs(sim_s - wall_s) < 0.02, (sim_s, wall_s)
    assert abs(sim_s - host_s) < 0.05, (sim_s, host_s)
    assert lead <= 200, lead
    s.cmd("OFF")


def test_parallel(sim_bin, firmware, workdir, report):
    sims = [Sim(sim_bin, firmware, workdir, f"par{i}") for i in range(2)]
    assert sims[0].pty_path != sims[1].pty_path
    errors = []

    def run(s, led):
        try:
            expect(s.read_line(3.0), "READY " + IDENT)
            for _ in range(20):
                expect(s.cmd(f"ON {led}"), f"OK ON {led}")
                on_only(s.levels(), led)
                expect(s.cmd("OFF"), "OK OFF")
            expect(s.cmd(f"ON {led}"), f"OK ON {led}")
        except Exception as e:  # noqa: BLE001 - report from the thread
            errors.append(e)

    threads = [threading.Thread(target=run, args=(s, led)) for s, led in zip(sims, (1, 8))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if not errors:
        on_only(sims[0].levels(), 1)
        on_only(sims[1].levels(), 8)
    for s in sims:
        expect(s.stop(), 0)
    if errors:
        raise errors[0]
    report["parallel instances"] = [s.pty_path for s in sims]


def test_watchdog(sim_bin, hang_fw, workdir, report):
    """Test build hangs on a BEL byte: the watchdog must reset the MCU, the
    LED must go off and the board must announce itself again."""
    s = Sim(sim_bin, hang_fw, workdir, "hang")
    try:
        expect(s.read_line(3.0), "READY " + IDENT)
        expect(s.cmd("ON 6"), "OK ON 6")
        t = time.monotonic()
        s.write(b"\x07")
        expect(s.read_line(2.0), "READY " + IDENT)
        report["watchdog: hang -> READY again (host ms)"] = round((time.monotonic() - t) * 1000, 1)
        on_only(s.levels(), None)
        assert any("# reset" in l for l in open(s.pin_log)), "no reset marker in pin log"
        expect(s.cmd("STATE"), "OK STATE OFF timeout=3000 tripped=0")
    finally:
        expect(s.stop(), 0)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--sim", required=True)
    ap.add_argument("--firmware", required=True)
    ap.add_argument("--hang-firmware")
    args = ap.parse_args()
    report = {}
    with tempfile.TemporaryDirectory(prefix="psscan-sim-test-") as workdir:
        s = Sim(args.sim, args.firmware, workdir, "main")
        try:
            steps = [
                ("basic", lambda: test_basic(s, report)),
                ("errors", lambda: test_errors(s)),
                ("timeout", lambda: test_timeout(s, report)),
                ("reopen", lambda: test_reopen(s)),
                ("realtime", lambda: test_realtime(s, report)),
            ]
            for name, fn in steps:
                fn()
                print(f"ok   {name}")
        except BaseException:
            print(open(s.stderr_path).read() if os.path.exists(s.stderr_path) else "", file=sys.stderr)
            raise
        finally:
            rc = s.stop()
        expect(rc, 0)
        print(open(s.stderr_path).read().strip().splitlines()[-1])
        test_parallel(args.sim, args.firmware, workdir, report)
        print("ok   parallel")
        if args.hang_firmware:
            test_watchdog(args.sim, args.hang_firmware, workdir, report)
            print("ok   watchdog")
    for k, v in report.items():
        print(f"  {k}: {v}")
    print("test_sim: all passed")


if __name__ == "__main__":
    main()
