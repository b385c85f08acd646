#!/usr/bin/env python3
"""A pymavlink 'vehicle' for markhold-autopilot's interop test.

It listens on UDP (127.0.0.1, port 0) or on a pseudo-terminal, prints where on its first
stdout line ("UDP <port>" or "PTY <path>"), sends ArduSub-like heartbeats and telemetry,
acknowledges arm / mode / stream commands, and checks what the link sends: sender system
id, GCS heartbeat type and rate, pilot-input channel map, PWM ranges and rate, neutral
before the final disarm. The run ends at the disarm (or the deadline); the verdict is a
JSON line on stdout and the exit status (0 = all checks passed).

`--scenario pilot` plays an ArduSub vehicle with a pilot beside it (QGroundControl as
system 255, component 190, seen through a router) for `markhold run`: it answers the
parameter protocol, emulates the pilot-input failsafe, captures markhold's STATUSTEXT,
and drives the pilot's actions from what markhold says (see pilot_main).
`--scenario params` answers heartbeats and parameters only, for `markhold preflight`.
`--scenario thrust` reads pilot input as ArduSub does per mode and channel (see
thrust_main) and turns it into T200 thrust from Blue Robotics' published table
(hil/data/t200-*.csv) at `--volts`, for the keeper's dead-zone compensation test.
"""
import argparse
import json
import os
import select
import socket
import sys
import time

from pymavlink.dialects.v20 import ardupilotmega as mav2


class Out:
    """File-like sink for pymavlink's *_send methods."""

    def __init__(self, send):
        self.send = send

    def write(self, data):
        self.send(bytes(data))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--mode", choices=["udp", "pty"], default="udp")
    ap.add_argument("--pilot", choices=["rc", "manual"], default="rc")
    ap.add_argument("--deadline", type=float, default=30.0)
    ap.add_argument("--scenario", choices=["interop", "pilot", "params", "thrust", "hold"], default="interop")
    ap.add_argument("--pilot-mode-after", type=float, default=-1.0,
                    help="hold scenario: the pilot selects STABILIZE this long after 'markhold on'")
    ap.add_argument("--volts", type=float, default=16.0, help="thrust scenario: supply voltage")
    ap.add_argument("--param", action="append", default=[], help="NAME=VALUE override")
    ap.add_argument("--no-pilot-after-exit", action="store_true")
    args = ap.parse_args()
    if args.scenario == "thrust":
        return thrust_main(args)
    if args.scenario == "hold":
        return hold_main(args)
    if args.scenario != "interop":
        return pilot_main(args)

    peer = [None]
    if args.mode == "udp":
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(("127.0.0.1", 0))
        sock.setblocking(False)
        print("UDP %d" % sock.getsockname()[1], flush=True)

        def send(b):
            if peer[0] is not None:
                sock.sendto(b, peer[0])

        def recv():
            r, _, _ = select.select([sock], [], [], 0.005)
            if not r:
                return b""
            data, addr = sock.recvfrom(4096)
            peer[0] = addr
            return data
    else:
        import tty

        master, slave = os.openpty()
        tty.setraw(slave)
        path = os.ttyname(slave)
        os.set_blocking(master, False)
        print("PTY %s" % path, flush=True)

        def send(b):
            try:
                os.write(master, b)
            except OSError:
                pass

        def recv():
            r, _, _ = select.select([master], [], [], 0.005)
            if not r:
                return b""
            try:
                return os.read(master, 4096)
            except OSError:
                return b""

    mav = mav2.MAVLink(Out(send), srcSystem=1, srcComponent=1)
    mav.robust_parsing = True

    failures = []
    armed = False
    mode = 0
    gcs_hb_times = []
    pilot = []  # (t, sysid, compid, fields)
    stream_ids = set()
    disarm_at = None
    neutral_before_disarm = None
    t0 = time.time()
    last_hb = 0.0

    while time.time() - t0 < args.deadline:
        now = time.time()
        if now - last_hb >= 0.1:
            last_hb = now
            base = mav2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mav2.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
            mav.heartbeat_send(mav2.MAV_TYPE_SUBMARINE, mav2.MAV_AUTOPILOT_ARDUPILOTMEGA, base, mode, mav2.MAV_STATE_ACTIVE)
            if stream_ids:
                mav.attitude_send(1234, 0.05, -0.04, 1.5, 0.0, 0.0, 0.2)
                # 3 m deep, fresh water (997 kg/m^3), 101325 Pa surface.
                mav.scaled_pressure2_send(1234, (101325.0 + 997.0 * 9.80665 * 3.0) / 100.0, 0.0, 1500)
                mav.servo_output_raw_send(1234, 0, 1100, 1200, 1300, 1400, 1500, 1600, 1700, 1800)
                mav.local_position_ned_send(1234, 1.0, -2.0, 3.0, 0.1, 0.2, 0.3)
        data = recv()
        if not data:
            if disarm_at is not None and now - disarm_at > 0.3:
                break
            continue
        try:
            msgs = mav.parse_buffer(data) or []
        except Exception as e:  # a frame pymavlink cannot decode is a failure
            failures.append("parse error: %r" % (e,))
            continue
        for m in msgs:
            t = m.get_type()
            src = (m.get_srcSystem(), m.get_srcComponent())
            if t == "BAD_DATA":
                failures.append("bad data from link")
                continue
            if t == "HEARTBEAT":
                gcs_hb_times.append(now)
                if m.type != mav2.MAV_TYPE_GCS or m.autopilot != mav2.MAV_AUTOPILOT_INVALID:
                    failures.append("heartbeat type %d autopilot %d" % (m.type, m.autopilot))
                if src[0] != 255:
                    failures.append("heartbeat from system %d" % src[0])
            elif t in ("RC_CHANNELS_OVERRIDE", "MANUAL_CONTROL"):
                if src[0] != 255:
                    failures.append("%s from system %d (ArduSub drops it)" % (t, src[0]))
                pilot.append((now, t, m))
            elif t == "COMMAND_LONG":
                if src[0] != 255:
                    failures.append("COMMAND_LONG from system %d" % src[0])
                if m.target_system != 1:
                    failures.append("COMMAND_LONG to system %d" % m.target_system)
                result = mav2.MAV_RESULT_ACCEPTED
                if m.command == mav2.MAV_CMD_COMPONENT_ARM_DISARM:
                    armed = m.param1 > 0.5
                    if not armed and disarm_at is None:
                        disarm_at = now
                        neutral_before_disarm = pilot[-1] if pilot else None
                elif m.command == mav2.MAV_CMD_DO_SET_MODE:
                    if int(m.param1) != 1:
                        failures.append("DO_SET_MODE param1 %r" % m.param1)
                    mode = int(m.param2)
                elif m.command == mav2.MAV_CMD_SET_MESSAGE_INTERVAL:
                    stream_ids.add(int(m.param1))
                mav.command_ack_send(m.command, result)

    # --- verdict ---
    if disarm_at is None:
        failures.append("no disarm received before the deadline")
    if not gcs_hb_times:
        failures.append("no GCS heartbeat")
    else:
        span = gcs_hb_times[-1] - gcs_hb_times[0]
        if len(gcs_hb_times) >= 2:
            rate = (len(gcs_hb_times) - 1) / span
            if not 0.7 <= rate <= 1.4:
                failures.append("heartbeat rate %.2f Hz" % rate)
    for want in (30, 32, 36, 137):
        if want not in stream_ids:
            failures.append("stream %d not requested" % want)
    if mode != 19:
        failures.append("mode %d, expected MANUAL (19)" % mode)

    # Pilot-input rate over the commanded period (wall clock, the link runs at 30 Hz).
    pilot_rate = 0.0
    if len(pilot) >= 2:
        pilot_rate = (len(pilot) - 1) / (pilot[-1][0] - pilot[0][0])
        if pilot_rate < 20.0:
            failures.append("pilot input %.1f Hz < 20 Hz" % pilot_rate)
    else:
        failures.append("no pilot input")

    seen = set()
    expected = None
    if args.pilot == "rc":
        # Channel map: 1 pitch, 2 roll, 3 throttle, 4 yaw, 5 forward, 6 lateral.
        expected = {(5, 1), (6, -1), (3, -1), (4, 1), (2, 1), (1, -1)}
        for _, t, m in pilot:
            if t != "RC_CHANNELS_OVERRIDE":
                failures.append("unexpected %s" % t)
                continue
            if (m.target_system, m.target_component) != (1, 1):
                failures.append("override to %d/%d" % (m.target_system, m.target_component))
            ch = [m.chan1_raw, m.chan2_raw, m.chan3_raw, m.chan4_raw, m.chan5_raw, m.chan6_raw]
            for c in ch:
                if not 1100 <= c <= 1900:
                    failures.append("pwm %d out of 1100..1900" % c)
            dev = [(i + 1, 1 if c > 1500 else -1, abs(c - 1500)) for i, c in enumerate(ch) if c != 1500]
            if len(dev) > 1:
                failures.append("several channels moved at once: %r" % (ch,))
            for i, s, mag in dev:
                seen.add((i, s))
                # Effort 0.5 in MANUAL: 30.5 us (past the 30 us dead band) + 0.5 * 369.5.
                if mag != 215:
                    failures.append("channel %d offset %d, expected 215" % (i, mag))
        last = neutral_before_disarm
        if last is None or [last[2].chan1_raw, last[2].chan2_raw, last[2].chan3_raw, last[2].chan4_raw,
                            last[2].chan5_raw, last[2].chan6_raw] != [1500] * 6:
            failures.append("last override before disarm not neutral")
    else:
        # MANUAL_CONTROL: x fwd, y lat, z throttle 0..1000 (500 neutral), r yaw, s pitch, t roll.
        expected = {("x", 1), ("y", -1), ("z", -1), ("r", 1), ("t", 1), ("s", -1)}
        for _, t, m in pilot:
            if t != "MANUAL_CONTROL":
                failures.append("unexpected %s" % t)
                continue
            if m.target != 1:
                failures.append("MANUAL_CONTROL target %d" % m.target)
            vals = {"x": m.x, "y": m.y, "z": m.z - 500, "r": m.r, "s": m.s, "t": m.t}
            for k, v in vals.items():
                lim = 500 if k == "z" else 1000
                if not -lim <= v <= lim:
                    failures.append("%s=%d out of range" % (k, v))
            dev = [(k, 1 if v > 0 else -1) for k, v in vals.items() if v != 0]
            if len(dev) > 1:
                failures.append("several axes moved at once: %r" % (vals,))
            seen.update(dev)
        last = neutral_before_disarm
        if last is None or (last[2].x, last[2].y, last[2].z, last[2].r, last[2].s, last[2].t) != (0, 0, 500, 0, 0, 0):
            failures.append("last MANUAL_CONTROL before disarm not neutral")
    if seen != expected:
        failures.append("axis map: saw %r expected %r" % (sorted(seen), sorted(expected)))

    verdict = {
        "ok": not failures,
        "failures": failures[:20],
        "heartbeats": len(gcs_hb_times),
        "pilot_inputs": len(pilot),
        "pilot_rate_hz": round(pilot_rate, 2),
        "streams": sorted(stream_ids),
    }
    print(json.dumps(verdict), flush=True)
    sys.exit(0 if not failures else 1)


# ArduSub parameters a BlueROV2 Heavy set up for markhold has (names as in ArduSub).
PARAMS = {
    "SYSID_MYGCS": 255.0,
    "FS_PILOT_INPUT": 2.0,
    "FS_PILOT_TIMEOUT": 3.0,
    "FS_GCS_ENABLE": 2.0,
    "FRAME_CONFIG": 2.0,
    "RC_OVERRIDE_TIME": 3.0,
    "EK3_SRC1_POSXY": 6.0,
    "EK3_SRC1_VELXY": 6.0,
    "EK3_SRC1_YAW": 1.0,
    "VISO_TYPE": 1.0,
}
PILOT = (255, 190)  # QGroundControl
MANUAL, STABILIZE = 19, 0


def pilot_main(args):
    params = dict(PARAMS)
    for kv in args.param:
        k, v = kv.split("=", 1)
        params[k] = float(v)
    names = sorted(params)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.setblocking(False)
    print("UDP %d" % sock.getsockname()[1], flush=True)
    peer = [None]

    def send(b):
        if peer[0] is not None:
            sock.sendto(b, peer[0])

    veh = mav2.MAVLink(Out(send), srcSystem=1, srcComponent=1)
    veh.robust_parsing = True
    # The pilot's QGroundControl: its packets reach markhold through the router.
    qgc = mav2.MAVLink(Out(send), srcSystem=PILOT[0], srcComponent=PILOT[1])
    sysid_mygcs = int(params["SYSID_MYGCS"])

    failures = []
    st = {"armed": False, "mode": MANUAL if args.scenario == "pilot" else STABILIZE}
    texts = []  # (t, severity, text) from markhold
    log = []  # (t, event)
    mh_inputs = []  # (t, kind) kind: "cmd" (non-neutral), "neutral", "release"
    last_accepted_input = [None]
    failsafe = []
    param_reads = [0]
    named = set()
    t0 = time.time()
    last_hb = 0.0
    last_js = 0.0
    last_heard = [None]
    # The pilot's plan, driven by what markhold says.
    plan = {"step": 0, "at": None, "deflect_until": None, "js": args.scenario == "pilot",
            "no_js_after_exit": args.no_pilot_after_exit}
    change_t = [None]

    def pilot_mode(m):
        now = time.time()
        log.append((round(now - t0, 3), "pilot mode %d" % m))
        # COMMAND_LONG from QGroundControl: the vehicle switches; the router shows it to
        # markhold too.
        qgc.command_long_send(1, 1, mav2.MAV_CMD_DO_SET_MODE, 0, 1, m, 0, 0, 0, 0, 0)
        st["mode"] = m
        st["hb_now"] = True
        change_t[0] = now

    def pilot_arm():
        log.append((round(time.time() - t0, 3), "pilot arm"))
        qgc.command_long_send(1, 1, mav2.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        st["armed"] = True

    def said(prefix, n=1):
        return sum(1 for _, _, x in texts if x.startswith(prefix)) >= n

    while time.time() - t0 < args.deadline:
        now = time.time()
        # ArduSub heartbeats at 1 Hz, and at once on a mode change (Sub::set_mode sends
        # MSG_HEARTBEAT): here the 1 Hz is 10 Hz to keep the run short, and a change sets
        # st["hb_now"].
        if now - last_hb >= 0.1 or st.pop("hb_now", False):
            last_hb = now
            base = mav2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mav2.MAV_MODE_FLAG_SAFETY_ARMED if st["armed"] else 0)
            # ArduSub reports CRITICAL while a failsafe is active (here: after the leak).
            status = mav2.MAV_STATE_CRITICAL if now < st.get("critical_until", 0) else mav2.MAV_STATE_ACTIVE
            veh.heartbeat_send(mav2.MAV_TYPE_SUBMARINE, mav2.MAV_AUTOPILOT_ARDUPILOTMEGA, base, st["mode"], status)
            veh.attitude_send(1234, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        # The pilot's joystick: QGroundControl sends MANUAL_CONTROL all the time, centred
        # unless the pilot deflects it.
        if plan["js"] and st["armed"] and now - last_js >= 0.05:
            last_js = now
            x = 600 if plan["deflect_until"] and now < plan["deflect_until"] else 0
            qgc.manual_control_send(1, x, 0, 500, 0, 0)
            if PILOT[0] == sysid_mygcs:
                last_accepted_input[0] = now
        # The pilot-input failsafe (FS_PILOT_INPUT), as ArduSub runs it.
        if st["armed"] and params["FS_PILOT_INPUT"] != 0 and last_accepted_input[0] is not None:
            if now - last_accepted_input[0] > params["FS_PILOT_TIMEOUT"]:
                failsafe.append(round(now - t0, 3))
                veh.statustext_send(mav2.MAV_SEVERITY_CRITICAL, b"Lost manual control")
                st["armed"] = False
        if args.scenario == "pilot":
            step_plan(plan, now, said, pilot_mode, pilot_arm, mh_inputs, change_t, failures)
            if plan.pop("vehicle_text", False):
                # What ArduSub says on a leak: markhold must log it.
                veh.statustext_send(mav2.MAV_SEVERITY_CRITICAL, b"Leak Detected!")
                st["critical_until"] = now + 0.3
        r, _, _ = select.select([sock], [], [], 0.005)
        if not r:
            if last_heard[0] is not None and now - last_heard[0] > 1.5:
                break
            continue
        data, addr = sock.recvfrom(4096)
        peer[0] = addr
        last_heard[0] = now
        try:
            msgs = veh.parse_buffer(data) or []
        except Exception as e:
            failures.append("parse error: %r" % (e,))
            continue
        for m in msgs:
            t = m.get_type()
            src = (m.get_srcSystem(), m.get_srcComponent())
            if t == "BAD_DATA":
                failures.append("bad data from link")
                continue
            if src == PILOT:
                failures.append("markhold sent as QGroundControl's ids %r" % (src,))
            if t == "STATUSTEXT":
                text = m.text if isinstance(m.text, str) else m.text.decode()
                texts.append((round(now - t0, 3), m.severity, text))
                if len(text.encode()) >= 50:
                    failures.append("statustext of %d bytes" % len(text.encode()))
            elif t == "NAMED_VALUE_FLOAT":
                named.add(m.name if isinstance(m.name, str) else m.name.decode())
            elif t == "RC_CHANNELS_OVERRIDE":
                ch = [m.chan1_raw, m.chan2_raw, m.chan3_raw, m.chan4_raw, m.chan5_raw, m.chan6_raw]
                kind = "release" if ch == [0] * 6 else ("neutral" if ch == [1500] * 6 else "cmd")
                mh_inputs.append((now, kind))
                if kind != "release" and src[0] == sysid_mygcs:
                    last_accepted_input[0] = now
            elif t == "MANUAL_CONTROL":
                kind = "neutral" if (m.x, m.y, m.z, m.r) == (0, 0, 500, 0) else "cmd"
                mh_inputs.append((now, kind))
                if src[0] == sysid_mygcs:
                    last_accepted_input[0] = now
            elif t == "PARAM_REQUEST_READ":
                param_reads[0] += 1
                pid = m.param_id if isinstance(m.param_id, str) else m.param_id.decode()
                if pid in params:
                    veh.param_value_send(pid.encode(), params[pid], mav2.MAV_PARAM_TYPE_REAL32, len(names), names.index(pid))
            elif t == "PARAM_REQUEST_LIST":
                for i, n in enumerate(names):
                    veh.param_value_send(n.encode(), params[n], mav2.MAV_PARAM_TYPE_REAL32, len(names), i)
            elif t == "COMMAND_LONG":
                result = mav2.MAV_RESULT_ACCEPTED
                if m.command == mav2.MAV_CMD_COMPONENT_ARM_DISARM:
                    st["armed"] = m.param1 > 0.5
                    log.append((round(now - t0, 3), "markhold arm %d" % st["armed"]))
                elif m.command == mav2.MAV_CMD_DO_SET_MODE:
                    st["mode"] = int(m.param2)
                    st["hb_now"] = True
                    log.append((round(now - t0, 3), "markhold mode %d" % st["mode"]))
                elif m.command == mav2.MAV_CMD_REQUEST_MESSAGE and int(m.param1) == 148:
                    veh.autopilot_version_send(0, (4 << 24) | (1 << 16) | (2 << 8) | 255, 0, 0, 0,
                                               [0] * 8, [0] * 8, [0] * 8, 0, 0, 0)
                veh.command_ack_send(m.command, result)

    verdict = {
        "ok": not failures,
        "failures": failures[:20],
        "texts": texts,
        "log": log,
        "failsafe": failsafe,
        "armed_at_end": st["armed"],
        "mode_at_end": st["mode"],
        "param_reads": param_reads[0],
        "named": sorted(named),
        "step": plan["step"],
        "inputs_after_mode_change": plan.get("after_change"),
        "inputs_while_off": plan.get("while_off"),
        "release_seen": plan.get("release"),
        "last_input_after_mode_change_ms": plan.get("last_input_ms"),
    }
    print(json.dumps(verdict), flush=True)
    sys.exit(0 if not failures else 1)


def step_plan(plan, now, said, pilot_mode, pilot_arm, mh_inputs, change_t, failures):
    """The pilot: arm and select MANUAL when markhold is ready; switch away (STABILIZE)
    once engaged; watch that markhold goes quiet; switch back (engaged again); move the
    stick (markhold lets go); switch away and back (engaged a third time); then markhold
    stops by itself at the end of its frames and hands back."""
    s = plan["step"]
    if s == 0 and said("markhold ready"):
        pilot_arm()
        # Already in MANUAL: switch away and back is not needed; arming in it engages.
        plan["step"], plan["at"] = 1, now
    elif s == 1 and said("markhold on", 1):
        plan["step"], plan["at"] = 2, now
        plan["vehicle_text"] = True
    elif s == 2 and now - plan["at"] > 0.5:
        pilot_mode(STABILIZE)
        plan["step"], plan["at"] = 3, now
    elif s == 3 and now - plan["at"] > 1.0:
        # What markhold sent after the pilot's mode change: at most what was in flight
        # and one neutral; then nothing but the release.
        after = [k for t, k in mh_inputs if t > change_t[0]]
        plan["after_change"] = after
        pilot_after = [t for t, k in mh_inputs if t > change_t[0] and k != "release"]
        plan["last_input_ms"] = round((max(pilot_after) - change_t[0]) * 1e3, 1) if pilot_after else 0.0
        plan["release"] = "release" in after
        # Judged by order, not by the wall clock (a loaded host delays everything): after
        # the change, at most the input already in flight and the one neutral, then
        # nothing but the release. At 30 frames/s that is within 2 frames (67 ms) of
        # markhold hearing the change; last_input_ms reports the wall-clock figure.
        if len([k for k in after if k != "release"]) > 2 or (after and after[-1] != "release"):
            failures.append("pilot input after the pilot's mode change: %r" % after[:8])
        if not said("markhold off: mode changed"):
            failures.append("no 'markhold off: mode changed'")
        plan["step"], plan["at"], plan["mark"] = 4, now, len(mh_inputs)
    elif s == 4 and now - plan["at"] > 1.0:
        # Left alone for a second in STABILIZE: markhold must not come back by itself.
        quiet = [k for _, k in mh_inputs[plan["mark"]:] if k != "release"]
        plan["while_off"] = len(quiet)
        if quiet or said("markhold on", 2):
            failures.append("markhold commanded while disengaged: %r" % quiet[:5])
        pilot_mode(MANUAL)
        plan["step"], plan["at"] = 5, now
    elif s == 5 and said("markhold on", 2):
        plan["step"], plan["at"] = 6, now
    elif s == 6 and now - plan["at"] > 0.5:
        plan["deflect_until"] = now + 0.3
        plan["step"], plan["at"] = 7, now
    elif s == 7 and said("markhold off: pilot input"):
        plan["step"], plan["at"] = 8, now
    elif s == 8 and now - plan["at"] > 0.4:
        pilot_mode(STABILIZE)
        plan["step"], plan["at"] = 9, now
    elif s == 9 and now - plan["at"] > 0.3:
        pilot_mode(MANUAL)
        plan["step"], plan["at"] = 10, now
    elif s == 10 and said("markhold on", 3):
        plan["step"] = 11
        if plan["no_js_after_exit"]:
            # Nobody at the joystick when markhold stops.
            plan["js"] = False


# --- ArduSub's pilot-input handling (written from ArduSub's source, see
# docs/design/hil.md): RC_Channel with MIN 1100, TRIM 1500, MAX 1900.
RC_DZ = {1: 30, 2: 30, 3: 30, 4: 40}  # RC1_DZ..RC4_DZ defaults
THR_DZ = 100
JS_GAIN = 0.5
ALT_HOLD = 2


def norm_input(pwm):
    """RC_Channel::norm_input: no dead zone."""
    v = (pwm - 1500) / 400.0
    return max(-1.0, min(1.0, v))


def c_div(a, b):
    """C integer division (truncates toward zero)."""
    q = abs(a) // abs(b)
    return q if (a >= 0) == (b > 0) else -q


def angle_dz(pwm, dz):
    """RC_Channel::pwm_to_angle_dz_trim: -4500..4500, zero within dz of trim."""
    r = max(1100, min(1900, pwm))
    hi, lo = 1500 + dz, 1500 - dz
    if r > hi:
        return c_div(4500 * (r - hi), 1900 - hi)
    if r < lo:
        return c_div(4500 * (r - lo), lo - 1100)
    return 0


def range_dz(pwm, dz):
    """RC_Channel::pwm_to_range_dz: 0..1000, the dead zone at the bottom."""
    r = max(1100, min(1900, pwm))
    low = 1100 + dz
    return c_div(1000 * (r - low), 1900 - low) if r > low else 0


def climb(pwm):
    """Sub::get_pilot_desired_climb_rate as a fraction of the speed limit."""
    ctrl = range_dz(pwm, RC_DZ[3])
    low = 1100 + RC_DZ[3]
    mid = c_div(1000 * (1500 - low), 1900 - low)
    top, bottom = mid + THR_DZ, mid - THR_DZ
    if ctrl < bottom:
        return (ctrl - bottom) / bottom
    if ctrl > top:
        return (ctrl - top) / (1000.0 - top)
    return 0.0


def mixer_inputs(mode, ch):
    """What reaches AP_Motors6DOF (forward, lateral, throttle, roll, pitch, yaw) from the
    channels ch[1..6] (1 pitch, 2 roll, 3 throttle, 4 yaw, 5 forward, 6 lateral). In the
    stabilized modes roll, pitch and yaw are setpoints, throttle in ALT_HOLD a climb
    rate: with the vehicle level and still, their loops ask nothing of the thrusters
    unless the input passes its dead zone (reported as 'setpoints')."""
    fwd, lat = norm_input(ch[5]), norm_input(ch[6])
    if mode == MANUAL:
        return (fwd, lat, norm_input(ch[3]), norm_input(ch[2]), norm_input(ch[1]), norm_input(ch[4])), {}
    yaw_dz = int(RC_DZ[4] * JS_GAIN)
    sp = {"roll": angle_dz(ch[2], RC_DZ[2]), "pitch": angle_dz(ch[1], RC_DZ[1]),
          "yaw": angle_dz(ch[4], yaw_dz)}
    thr = 0.0
    if mode == STABILIZE:
        thr = norm_input(ch[3])
    else:
        sp["climb"] = climb(ch[3])
    return (fwd, lat, thr, 0.0, 0.0, 0.0), sp


# Motors 1-4 of both BlueROV2 frames: (yaw, forward, lateral) factors and the thrust
# direction's forward component (horizontal thrusters at 45 degrees).
HORIZONTAL = [((1, -1, 1), -0.7071), ((-1, -1, -1), -0.7071), ((-1, 1, 1), 0.7071), ((1, 1, -1), 0.7071)]


def load_t200(volts):
    """Thrust (N) per PWM row of Blue Robotics' table, interpolated linearly in voltage."""
    here = os.path.dirname(os.path.abspath(__file__))
    sheets = {}
    for v in (10, 12, 14, 16, 18, 20):
        rows = {}
        with open(os.path.join(here, "..", "..", "hil", "data", "t200-%dv.csv" % v)) as f:
            for line in f:
                if line[:1].isdigit():
                    c = line.split(",")
                    rows[int(c[0])] = float(c[5]) * 9.80665
        sheets[v] = rows
    volts = max(10.0, min(20.0, volts))
    lo = max(v for v in sheets if v <= volts)
    hi = min(v for v in sheets if v >= volts)
    w = 0.0 if hi == lo else (volts - lo) / (hi - lo)
    return {p: sheets[lo][p] + w * (sheets[hi][p] - sheets[lo][p]) for p in sheets[lo]}


def thrust_at(table, pwm):
    pwm = max(1100, min(1900, pwm))
    r = 1100 + 4 * ((pwm - 1100) // 4)
    if r == 1900:
        return table[1900]
    return table[r] + (pwm - r) / 4.0 * (table[r + 4] - table[r])


def thrust_main(args):
    """An ArduSub vehicle at rest: acknowledges mode and arm commands, reads pilot input
    from the GCS id per mode, mixes the thruster channels as AP_Motors6DOF does (PWM =
    1500 + 400 x output, truncated) and records the T200 thrust at `--volts`. Ends 1 s
    after the link falls silent; the verdict lists every distinct input it saw."""
    table = load_t200(args.volts)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.setblocking(False)
    print("UDP %d" % sock.getsockname()[1], flush=True)
    peer = [None]

    def send(b):
        if peer[0] is not None:
            sock.sendto(b, peer[0])

    veh = mav2.MAVLink(Out(send), srcSystem=1, srcComponent=1)
    veh.robust_parsing = True
    st = {"armed": False, "mode": MANUAL}
    ch = {i: 1500 for i in range(1, 9)}
    samples = {}
    failures = []
    t0 = time.time()
    last_hb, last_heard = 0.0, None

    def record(kind):
        inputs, sp = mixer_inputs(st["mode"], ch)
        fwd, lat, _, _, _, yaw = inputs
        horz = [yaw * f[0] + fwd * f[1] + lat * f[2] for f, _ in HORIZONTAL]
        scale = max([1.0] + [abs(h) for h in horz])
        motors = [int(1500 + 400 * (h / scale)) for h in horz]
        fx = sum(thrust_at(table, m) * dx for m, (_, dx) in zip(motors, HORIZONTAL))
        key = (kind, st["mode"], tuple(ch[i] for i in range(1, 7)))
        samples[key] = {"input": kind, "mode": st["mode"], "rc": [ch[i] for i in range(1, 7)],
                        "motors": motors, "fx_n": fx, "setpoints": sp}

    while time.time() - t0 < args.deadline:
        now = time.time()
        if now - last_hb >= 0.1:
            last_hb = now
            base = mav2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mav2.MAV_MODE_FLAG_SAFETY_ARMED if st["armed"] else 0)
            veh.heartbeat_send(mav2.MAV_TYPE_SUBMARINE, mav2.MAV_AUTOPILOT_ARDUPILOTMEGA, base, st["mode"], mav2.MAV_STATE_ACTIVE)
            veh.attitude_send(1234, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        r, _, _ = select.select([sock], [], [], 0.005)
        if not r:
            if last_heard is not None and now - last_heard > 1.0:
                break
            continue
        data, addr = sock.recvfrom(4096)
        peer[0], last_heard = addr, now
        for m in veh.parse_buffer(data) or []:
            t = m.get_type()
            if m.get_srcSystem() != 255:
                continue  # ArduSub uses pilot input from SYSID_MYGCS only
            if t == "RC_CHANNELS_OVERRIDE":
                raw = [m.chan1_raw, m.chan2_raw, m.chan3_raw, m.chan4_raw, m.chan5_raw, m.chan6_raw]
                for i, v in enumerate(raw):
                    if v not in (0, 65535):
                        ch[i + 1] = v
                if raw != [0] * 6:
                    record("rc")
            elif t == "MANUAL_CONTROL":
                # Sub::transform_manual_control_to_rc_override: scaled by the gain,
                # truncated by the conversion to int16.
                rpy = 0.4 * JS_GAIN
                thr = 0.8 * JS_GAIN
                ax = lambda v: max(1100, min(1900, int(1500 + v * rpy)))
                ch[3] = max(1100, min(1900, int(1500 - 500 * thr + m.z * thr)))
                ch[4], ch[5], ch[6] = ax(m.r), ax(m.x), ax(m.y)
                if m.enabled_extensions & 1:
                    ch[1] = ax(m.s)
                if m.enabled_extensions & 2:
                    ch[2] = ax(m.t)
                record("manual_control")
            elif t == "COMMAND_LONG":
                if m.command == mav2.MAV_CMD_COMPONENT_ARM_DISARM:
                    st["armed"] = m.param1 > 0.5
                elif m.command == mav2.MAV_CMD_DO_SET_MODE:
                    st["mode"] = int(m.param2)
                veh.command_ack_send(m.command, mav2.MAV_RESULT_ACCEPTED)
    verdict = {"ok": not failures, "failures": failures, "volts": args.volts,
               "samples": list(samples.values())}
    print(json.dumps(verdict), flush=True)
    sys.exit(0 if not failures else 1)


def hold_main(args):
    """`--scenario hold`: ArduSub as a live run sees it, for markhold's field-loop tests.
    HEARTBEAT at 1 Hz (ArduSub's rate) and ATTITUDE at 10 Hz, arm and mode commands
    acknowledged, the pilot-input failsafe (FS_PILOT_TIMEOUT 3 s) emulated. It records
    markhold's STATUSTEXT and every pilot input from SYSID_MYGCS with its arrival time
    ("cmd", "neutral", "release"). With --pilot-mode-after S the pilot (QGroundControl,
    255/190) selects STABILIZE S seconds after markhold says it is on. Ends 1.5 s after
    markhold falls silent (or at the deadline); the verdict is the record."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.setblocking(False)
    print("UDP %d" % sock.getsockname()[1], flush=True)
    peer = [None]

    def send(b):
        if peer[0] is not None:
            sock.sendto(b, peer[0])

    veh = mav2.MAVLink(Out(send), srcSystem=1, srcComponent=1)
    veh.robust_parsing = True
    qgc = mav2.MAVLink(Out(send), srcSystem=PILOT[0], srcComponent=PILOT[1])
    st = {"armed": False, "mode": MANUAL}
    texts, inputs, failsafe, log = [], [], [], []
    t0 = time.time()
    last_hb = last_att = 0.0
    last_heard = None
    last_input = None
    on_at = None
    pilot_done = False
    while time.time() - t0 < args.deadline:
        now = time.time()
        if now - last_hb >= 1.0 or st.pop("hb_now", False):
            last_hb = now
            base = mav2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mav2.MAV_MODE_FLAG_SAFETY_ARMED if st["armed"] else 0)
            veh.heartbeat_send(mav2.MAV_TYPE_SUBMARINE, mav2.MAV_AUTOPILOT_ARDUPILOTMEGA, base, st["mode"], mav2.MAV_STATE_ACTIVE)
        if now - last_att >= 0.1:
            last_att = now
            veh.attitude_send(int((now - t0) * 1000) & 0xFFFFFFFF, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        if st["armed"] and last_input is not None and now - last_input > 3.0:
            failsafe.append(round(now - t0, 3))
            veh.statustext_send(mav2.MAV_SEVERITY_CRITICAL, b"Lost manual control")
            st["armed"] = False
        if on_at is not None and not pilot_done and args.pilot_mode_after >= 0 and now - on_at >= args.pilot_mode_after:
            pilot_done = True
            log.append((round(now - t0, 3), "pilot mode %d" % STABILIZE))
            qgc.command_long_send(1, 1, mav2.MAV_CMD_DO_SET_MODE, 0, 1, STABILIZE, 0, 0, 0, 0, 0)
            st["mode"] = STABILIZE
            st["hb_now"] = True
        r, _, _ = select.select([sock], [], [], 0.005)
        if not r:
            if last_heard is not None and now - last_heard > 1.5:
                break
            continue
        data, addr = sock.recvfrom(4096)
        peer[0], last_heard = addr, now
        for m in veh.parse_buffer(data) or []:
            t = m.get_type()
            if t == "BAD_DATA":
                continue
            if t == "STATUSTEXT":
                # Whatever id markhold speaks as; pilot input counts only from SYSID_MYGCS.
                text = m.text if isinstance(m.text, str) else m.text.decode()
                texts.append((round(now - t0, 3), m.severity, text))
                if text.startswith("markhold on") and on_at is None:
                    on_at = now
            elif m.get_srcSystem() != 255:
                continue
            elif t == "RC_CHANNELS_OVERRIDE":
                ch = [m.chan1_raw, m.chan2_raw, m.chan3_raw, m.chan4_raw, m.chan5_raw, m.chan6_raw]
                kind = "release" if ch == [0] * 6 else ("neutral" if ch == [1500] * 6 else "cmd")
                inputs.append((round(now - t0, 4), kind))
                if kind != "release":
                    last_input = now
            elif t == "MANUAL_CONTROL":
                kind = "neutral" if (m.x, m.y, m.z, m.r) == (0, 0, 500, 0) else "cmd"
                inputs.append((round(now - t0, 4), kind))
                last_input = now
            elif t == "COMMAND_LONG":
                if m.command == mav2.MAV_CMD_COMPONENT_ARM_DISARM:
                    # Seen in the next 1 Hz heartbeat (a mode change sends one at once).
                    st["armed"] = m.param1 > 0.5
                    log.append((round(now - t0, 3), "markhold arm %d" % st["armed"]))
                elif m.command == mav2.MAV_CMD_DO_SET_MODE:
                    st["mode"] = int(m.param2)
                    st["hb_now"] = True
                    log.append((round(now - t0, 3), "markhold mode %d" % st["mode"]))
                veh.command_ack_send(m.command, mav2.MAV_RESULT_ACCEPTED)
    verdict = {"ok": not failsafe, "texts": texts, "inputs": inputs, "failsafe": failsafe,
               "log": log, "armed_at_end": st["armed"], "t0_epoch": t0,
               "on_at": None if on_at is None else round(on_at - t0, 3)}
    print(json.dumps(verdict), flush=True)
    sys.exit(0)


if __name__ == "__main__":
    main()
