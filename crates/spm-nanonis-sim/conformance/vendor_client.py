"""Conformance of nanonis-sim with the vendor's own Python client.

Drives `nanonis_spm.Nanonis` (PyPI `nanonis-spm`, the client SPECS ships) through a
scripted session against a running `nanonis-sim` and compares every value the vendor
client decodes with the truth: what was set (read-backs), the manual's relations, and
what the server's simulator says. The truth comes from the harness that started the
server (`cargo run -p spm-nanonis-sim --example vendor_conformance`), asked over this
process's stdin/stdout one line at a time ("truth <what>" -> one line of numbers).

Every command the server implements is exercised; a few it does not implement must get
an error the vendor client decodes without raising. Exit status 0 only when every
command interoperates. Run it through the harness (see crates/spm-nanonis-sim/README.md).
"""

import argparse
import socket
import struct
import sys
import traceback

# The vendor client prints errors on stdout; stdout is the harness's channel.
PROTOCOL = sys.stdout
sys.stdout = sys.stderr

import nanonis_spm  # noqa: E402  (after the redirect: it prints on import in some versions)

# The commands nanonis-sim implements (its dispatch table).
IMPLEMENTED = [
    "Util.VersionGet", "Piezo.CalibrGet", "Piezo.RangeGet", "Piezo.DriftCompSet",
    "Piezo.DriftCompGet", "Piezo.TiltSet", "Piezo.TiltGet", "Piezo.HystOnOffSet",
    "Piezo.HystOnOffGet", "Scan.Action", "Scan.StatusGet", "Scan.WaitEndOfScan",
    "Scan.FrameSet", "Scan.FrameGet", "Scan.BufferSet", "Scan.BufferGet", "Scan.PropsSet",
    "Scan.PropsGet", "Scan.SpeedSet", "Scan.SpeedGet", "Scan.FrameDataGrab",
    "Scan.XYPosGet", "FolMe.XYPosSet", "FolMe.XYPosGet", "FolMe.SpeedSet",
    "FolMe.SpeedGet", "FolMe.Stop", "ZCtrl.ZPosGet", "ZCtrl.OnOffSet", "ZCtrl.OnOffGet",
    "Motor.StartMove", "Motor.StopMove", "Motor.FreqAmpGet", "Signals.ValsGet",
]

failures = {}
seen = set()


def truth(what):
    PROTOCOL.write("truth " + what + "\n")
    PROTOCOL.flush()
    line = sys.stdin.readline()
    if not line:
        raise RuntimeError("the harness closed the truth channel")
    return [float(v) for v in line.split()]


def f32(x):
    return struct.unpack(">f", struct.pack(">f", x))[0]


def fail(command, message):
    failures.setdefault(command, []).append(message)
    print(f"FAIL {command}: {message}", file=sys.stderr)


def check(command, ok, message):
    if not ok:
        fail(command, message)


def call(command, method, *args, expect_error=False):
    """Calls a vendor-client method; returns its decoded variables (or None)."""
    seen.add(command)
    try:
        result = method(*args)
    except Exception as e:  # the vendor client raised: no interoperation
        fail(command, f"the vendor client raised {type(e).__name__}: {e}")
        traceback.print_exc()
        return None
    if len(result) != 3:
        fail(command, f"no reply decoded: {result!r}")
        return None
    error, _raw, values = result
    if expect_error:
        check(command, error != "", "an error was expected, none came")
    else:
        check(command, error == "", f"unexpected error {error!r}")
    return values


def close(a, b, rel=1e-6, absolute=0.0):
    return abs(a - b) <= rel * max(abs(a), abs(b)) + absolute


def session(n):
    # -- Util.VersionGet: the vendor's method declares its strings as "+*c", which its own
    # parser cannot decode (struct.error on any server); the same reply through the
    # vendor's machinery with the manual's layout (size, string, size, string, 2 × u32).
    seen.add("Util.VersionGet")
    try:
        n.Util_VersionGet()
        vendor_ok = True
    except struct.error:
        vendor_ok = False
    print(f"note: Util_VersionGet of nanonis-spm decodes: {vendor_ok}", file=sys.stderr)
    v = call("Util.VersionGet", n.quickSend, "Util.VersionGet", [], [],
             ["i", "*-c", "i", "*-c", "I", "I"])
    if v:
        check("Util.VersionGet", v[1].startswith("Nanonis SPM Control Software"), repr(v))
        check("Util.VersionGet", v[4] == 14718, f"host release {v[4]}")

    # -- Piezo: calibration and range (manual: range = calibration × 20 V).
    cal = truth("calibration")
    v = call("Piezo.CalibrGet", n.Piezo_CalibrGet)
    if v:
        check("Piezo.CalibrGet", v == [f32(c) for c in cal], f"{v} vs {cal}")
    v = call("Piezo.RangeGet", n.Piezo_RangeGet)
    if v:
        check("Piezo.RangeGet", all(close(r, f32(c * 20.0)) for r, c in zip(v, cal)),
              f"{v} vs {cal} × 20 V")
    z_half_m = cal[2] * 20.0 / 2.0

    v = call("Piezo.DriftCompGet", n.Piezo_DriftCompGet)
    if v:
        check("Piezo.DriftCompGet", v[0] == 1, f"found {v}")
    call("Piezo.DriftCompSet", n.Piezo_DriftCompSet, 2, 0.0, 0.0, 0.0, 12.5)
    v = call("Piezo.DriftCompGet", n.Piezo_DriftCompGet)
    if v:
        check("Piezo.DriftCompGet", v[0] == 0 and v[1:4] == [0.0, 0.0, 0.0] and v[7] == 12.5,
              f"after setting: {v}")
    call("Piezo.TiltSet", n.Piezo_TiltSet, 0.5, -0.25)
    v = call("Piezo.TiltGet", n.Piezo_TiltGet)
    check("Piezo.TiltGet", v == [0.5, -0.25], f"{v}")
    call("Piezo.TiltSet", n.Piezo_TiltSet, 0.0, 0.0)
    v = call("Piezo.TiltGet", n.Piezo_TiltGet)
    check("Piezo.TiltGet", v == [0.0, 0.0], f"{v}")
    call("Piezo.HystOnOffSet", n.Piezo_HystOnOffSet, 0)
    v = call("Piezo.HystOnOffGet", n.Piezo_HystOnOffGet)
    check("Piezo.HystOnOffGet", v == [0], f"{v}")

    # -- Scan properties, module list in the vendor's encoding.
    modules = ["Z-Controller", "Bias"]
    call("Scan.PropsSet", n.Scan_PropsSet, 2, 2, 3, "conformance", "a comment", modules, 3)
    # nanonis-spm 1.0.9's Scan_PropsGet declares the parameters-per-module array "*+i",
    # which its parser treats as a string array (adding a list to its offset): it raises
    # TypeError on any server. The same reply through the vendor's machinery with the int
    # array declared as its other arrays are ("*i").
    seen.add("Scan.PropsGet")
    try:
        n.Scan_PropsGet()
        vendor_ok = True
    except TypeError:
        vendor_ok = False
    print(f"note: Scan_PropsGet of nanonis-spm decodes: {vendor_ok}", file=sys.stderr)
    v = call("Scan.PropsGet", n.quickSend, "Scan.PropsGet", [], [],
             ["I", "I", "I", "i", "*-c", "i", "*-c", "i", "i", "*+c", "i", "*i", "i", "i",
              "*+c", "I"])
    if v:
        check("Scan.PropsGet", v[0:3] == [0, 0, 2], f"continuous, bouncy, autosave {v[0:3]}")
        check("Scan.PropsGet", v[4] == "conformance" and v[6] == "a comment", f"{v}")
        check("Scan.PropsGet", v[9] == modules, f"modules {v[9]}")
        check("Scan.PropsGet", v[-1] == 2, f"autopaste {v[-1]}")

    # -- Buffer: pixels coerced to a multiple of 16 (manual).
    call("Scan.BufferSet", n.Scan_BufferSet, [30], 100, 40)
    v = call("Scan.BufferGet", n.Scan_BufferGet)
    check("Scan.BufferGet", v == [1, [(30,)], 96, 40], f"{v}")
    call("Scan.BufferSet", n.Scan_BufferSet, [30], 32, 16)
    v = call("Scan.BufferGet", n.Scan_BufferGet)
    check("Scan.BufferGet", v == [1, [(30,)], 32, 16], f"{v}")

    frame = [f32(2e-8), f32(-1e-8), f32(0.64e-8), f32(0.32e-8), 0.0]
    call("Scan.FrameSet", n.Scan_FrameSet, *frame)
    v = call("Scan.FrameGet", n.Scan_FrameGet)
    check("Scan.FrameGet", v == frame, f"{v} vs {frame}")

    line_s = 0.0032  # 1e-4 s per pixel
    call("Scan.SpeedSet", n.Scan_SpeedSet, 0.0, 0.0, line_s, line_s, 2, 1.0)
    v = call("Scan.SpeedGet", n.Scan_SpeedGet)
    if v:
        check("Scan.SpeedGet", close(v[2], line_s) and close(v[3], line_s), f"{v}")
        check("Scan.SpeedGet", close(v[0], frame[2] / line_s, 1e-5), f"speed {v[0]}")
    scan_speed = v[0] if v else 1e-7

    # -- Clock and signals.
    t = truth("now")[0]
    v = call("Signals.ValsGet", n.Signals_ValsGet, [126, 127], 0)
    if v:
        check("Signals.ValsGet", v[0] == 2, f"{v}")
        clock = v[1][0][0] + v[1][1][0]
        check("Signals.ValsGet", abs(clock - t) < 1e-6 + 1e-7 * t, f"{clock} vs {t}")

    def now():
        v = n.Signals_ValsGet([126, 127], 0)[2]
        return v[1][0][0] + v[1][1][0]

    # -- Follow Me.
    call("FolMe.SpeedSet", n.FolMe_SpeedSet, 2.5e-8, 1)
    v = call("FolMe.SpeedGet", n.FolMe_SpeedGet)
    check("FolMe.SpeedGet", v == [f32(2.5e-8), 1], f"{v}")
    target = (3e-8, -2e-8)
    call("FolMe.XYPosSet", n.FolMe_XYPosSet, target[0], target[1], 1)
    v = call("FolMe.XYPosGet", n.FolMe_XYPosGet, 1)
    p = truth("position")
    if v:
        check("FolMe.XYPosGet", close(v[0], p[0], 1e-9, 1e-15) and close(v[1], p[1], 1e-9, 1e-15),
              f"{v} vs simulator {p}")
        check("FolMe.XYPosGet", close(v[0], target[0], 1e-9) and close(v[1], target[1], 1e-9),
              f"{v} vs target {target}")
    v = call("Scan.XYPosGet", n.Scan_XYPosGet, 1)
    check("Scan.XYPosGet", v == [f32(p[0]), f32(p[1])], f"{v} vs {p}")
    # "Use scan speed": the move takes distance / scan speed (+ 2 ms call overhead).
    call("FolMe.SpeedSet", n.FolMe_SpeedSet, 0.0, 0)
    v = call("FolMe.SpeedGet", n.FolMe_SpeedGet)
    check("FolMe.SpeedGet", v is not None and v[1] == 0, f"{v}")
    t0 = now()
    call("FolMe.XYPosSet", n.FolMe_XYPosSet, target[0] - 1e-8, target[1], 0)
    dt = now() - t0
    check("FolMe.XYPosSet", close(dt, 1e-8 / scan_speed + 0.002, 1e-3), f"{dt} s")
    call("FolMe.Stop", n.FolMe_Stop)
    # Out of range: refused by this command, not the next.
    call("FolMe.XYPosSet", n.FolMe_XYPosSet, 1.0, 0.0, 1, expect_error=True)

    # -- Z controller.
    v = call("ZCtrl.OnOffGet", n.ZCtrl_OnOffGet)
    check("ZCtrl.OnOffGet", v == [1], f"{v}")
    call("ZCtrl.OnOffSet", n.ZCtrl_OnOffSet, 0)
    v = call("ZCtrl.OnOffGet", n.ZCtrl_OnOffGet)
    check("ZCtrl.OnOffGet", v == [0], f"{v}")
    call("ZCtrl.OnOffSet", n.ZCtrl_OnOffSet, 1)
    v = call("ZCtrl.OnOffGet", n.ZCtrl_OnOffGet)
    check("ZCtrl.OnOffGet", v == [1], f"{v}")
    z = truth("z")[0]
    v = call("ZCtrl.ZPosGet", n.ZCtrl_ZPosGet)
    if v:
        check("ZCtrl.ZPosGet", abs(v[0] - z) < 0.1e-9, f"{v[0]} vs simulator {z}")

    # -- Scans: up (both halves), down, paused and resumed.
    def frame_check(direction_up, forward):
        v = call("Scan.FrameDataGrab", n.Scan_FrameDataGrab, 30, forward)
        if not v:
            return
        rows, columns, data, up = v[2], v[3], v[4], v[5]
        expected = truth(f"grab {forward}")
        check("Scan.FrameDataGrab", v[1] == "Z (m)", f"channel {v[1]!r}")
        check("Scan.FrameDataGrab", [rows, columns, up] == [int(x) for x in expected[:3]],
              f"{rows} × {columns}, up {up} vs {expected[:3]}")
        check("Scan.FrameDataGrab", up == direction_up, f"direction {up}")
        flat = [float(x) for x in data.flatten()]
        truth_data = [f32(x) for x in expected[3:]]
        differ = sum(1 for a, b in zip(flat, truth_data) if a != b)
        check("Scan.FrameDataGrab", len(flat) == len(truth_data) and differ == 0,
              f"{differ} of {len(flat)} values differ from the simulator's")
        check("Scan.FrameDataGrab", all(abs(x) <= z_half_m * (1 + 1e-6) for x in flat),
              "data beyond the Z range")

    v = call("Scan.StatusGet", n.Scan_StatusGet)
    check("Scan.StatusGet", v == [0], f"before a scan: {v}")
    t0 = now()
    call("Scan.Action", n.Scan_Action, 0, 1)
    v = call("Scan.StatusGet", n.Scan_StatusGet)
    check("Scan.StatusGet", v == [1], f"right after the start: {v}")
    v = call("Scan.WaitEndOfScan", n.Scan_WaitEndOfScan, 60000)
    check("Scan.WaitEndOfScan", v is not None and v[0] == 0 and v[2] == "", f"{v}")
    v = call("Scan.StatusGet", n.Scan_StatusGet)
    check("Scan.StatusGet", v == [0], f"after the end: {v}")
    frame_check(1, 1)
    frame_check(1, 0)
    duration = now() - t0
    check("Scan.Action", duration >= 16 * 2 * line_s, f"the scan took {duration} s")

    call("Scan.Action", n.Scan_Action, 0, 0)
    call("Scan.WaitEndOfScan", n.Scan_WaitEndOfScan, 60000)
    frame_check(0, 1)
    frame_check(0, 0)

    call("Scan.Action", n.Scan_Action, 0, 1)
    call("Scan.Action", n.Scan_Action, 2, 1)
    v = call("Scan.StatusGet", n.Scan_StatusGet)
    check("Scan.StatusGet", v == [1], f"paused: {v}")
    v = call("Scan.WaitEndOfScan", n.Scan_WaitEndOfScan, 20)
    check("Scan.WaitEndOfScan", v is not None and v[0] == 1, f"paused, no end of scan: {v}")
    call("Scan.Action", n.Scan_Action, 3, 1)
    v = call("Scan.WaitEndOfScan", n.Scan_WaitEndOfScan, 60000)
    check("Scan.WaitEndOfScan", v is not None and v[0] == 0, f"resumed: {v}")
    frame_check(1, 1)
    # A frame turned by 30° (clockwise), and back.
    call("Scan.FrameSet", n.Scan_FrameSet, *frame[:4], 30.0)
    v = call("Scan.FrameGet", n.Scan_FrameGet)
    check("Scan.FrameGet", v == frame[:4] + [30.0], f"{v}")
    call("Scan.Action", n.Scan_Action, 0, 1)
    call("Scan.WaitEndOfScan", n.Scan_WaitEndOfScan, 60000)
    frame_check(1, 1)
    call("Scan.FrameSet", n.Scan_FrameSet, *frame)
    call("Scan.Action", n.Scan_Action, 0, 1)
    call("Scan.Action", n.Scan_Action, 1, 1)
    v = call("Scan.StatusGet", n.Scan_StatusGet)
    check("Scan.StatusGet", v == [0], f"stopped: {v}")

    # -- Coarse motor.
    v = call("Motor.FreqAmpGet", n.Motor_FreqAmpGet, 3)
    check("Motor.FreqAmpGet", v is not None and v[0] > 0 and v[1] > 0, f"{v}")
    step_s = truth("motor_step_time")[0]
    for direction in (0, 1, 2, 3, 5, 4):
        t0 = now()
        call("Motor.StartMove", n.Motor_StartMove, direction, 3, 0, 1)
        dt = now() - t0
        check("Motor.StartMove", dt >= 3 * step_s, f"direction {direction}: {dt} s")
    call("Motor.StopMove", n.Motor_StopMove)
    z = truth("z")[0]
    v = call("ZCtrl.ZPosGet", n.ZCtrl_ZPosGet)
    if v:
        check("ZCtrl.ZPosGet", abs(v[0] - z) < 0.1e-9, f"{v[0]} vs simulator {z}")

    # -- Commands nanonis-sim does not implement: an error the vendor client decodes.
    unimplemented = [
        ("Bias.Get", n.Bias_Get, ()),
        ("Bias.Set", n.Bias_Set, (0.1,)),
        ("Current.Get", n.Current_Get, ()),
        ("ZCtrl.SetpntGet", n.ZCtrl_SetpntGet, ()),
    ]
    for command, method, args in unimplemented:
        try:
            result = method(*args)
            error = result[0] if len(result) == 3 else ""
            if "does not implement" not in error:
                fail(command, f"error {error!r} is not the server's")
        except Exception as e:
            fail(command, f"the vendor client raised {type(e).__name__}: {e}")
    # An unknown name altogether, through the vendor's machinery.
    result = n.quickSend("Nonexistent.Command", [], [], [])
    if len(result) != 3 or "does not implement" not in result[0]:
        fail("Nonexistent.Command", f"{result!r}")


class Recorder:
    """The vendor client's socket, recording every request it sends and the bytes it
    reads back (one exchange per request)."""

    def __init__(self, connection):
        self.connection = connection
        self.exchanges = []

    def send(self, data):
        self.exchanges.append([bytes(data), b""])
        return self.connection.send(data)

    def recv(self, n):
        data = self.connection.recv(n)
        if self.exchanges:
            self.exchanges[-1][1] += data
        return data

    def settimeout(self, t):
        self.connection.settimeout(t)

    def close(self):
        self.connection.close()

    def write(self, path):
        with open(path, "w") as f:
            f.write("# nanonis-spm 1.0.9 against nanonis-sim (crates/spm-nanonis-sim/conformance):\n")
            f.write("# per exchange, '>' the request frame the vendor client sent, '<' the reply.\n")
            for request, reply in self.exchanges:
                f.write("> " + request.hex() + "\n")
                f.write("< " + reply.hex() + "\n")


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--capture", help="write the frames exchanged to this file")
    args = parser.parse_args()
    connection = Recorder(socket.create_connection(("127.0.0.1", args.port), timeout=30))
    n = nanonis_spm.Nanonis(connection)
    try:
        session(n)
    except Exception as e:
        traceback.print_exc()
        fail("session", f"{type(e).__name__}: {e}")
    finally:
        connection.close()
        if args.capture:
            connection.write(args.capture)
    missing = [c for c in IMPLEMENTED if c not in seen]
    for c in missing:
        fail(c, "not exercised")
    good = [c for c in IMPLEMENTED if c not in failures]
    print(f"{len(good)} of {len(IMPLEMENTED)} commands interoperate with the vendor client",
          file=sys.stderr)
    other = sorted(set(failures) - set(IMPLEMENTED))
    if other:
        print(f"failures outside the implemented commands: {other}", file=sys.stderr)
    PROTOCOL.write(f"result {len(good)} {len(IMPLEMENTED)} {len(failures)}\n")
    PROTOCOL.flush()
    return 0 if not failures else 1


if __name__ == "__main__":
    sys.exit(main())
