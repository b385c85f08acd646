#!/usr/bin/env python3
"""A pymavlink 'vehicle' for markhold-autopilot's interop test.

It listens on UDP (127.0.0.1, port 0) or on a pseudo-terminal, prints where on its first
stdout line ("UDP <port>" or "PTY <path>"), sends ArduSub-like heartbeats and telemetry,
acknowledges arm / mode / stream commands, and checks what the link sends: sender system
id, GCS heartbeat type and rate, pilot-input channel map, PWM ranges and rate, neutral
before the final disarm. The run ends at the disarm (or the deadline); the verdict is a
JSON line on stdout and the exit status (0 = all checks passed).

`--scenario pilot` plays an ArduSub vehicle with a pilot beside it (QGroundControl as
system 255, component 190, seen through a router) for `markhold run` and `markhold hil
--vehicle`: it answers the parameter protocol, applies pilot input and runs the
pilot-input and GCS failsafes as ArduSub does (ArduSubInput, GcsFailsafe), captures
what markhold sends and as whom, and drives the pilot's actions from what markhold says
(see pilot_main; `station`, `takeover` and `noplan` are shorter plans).
`--scenario params` answers heartbeats and parameters only, for `markhold preflight`.
`--scenario exit` applies pilot input over UDP, TCP or a pseudo-terminal, session after
session, and reports the input each session left applied (see exit_main).
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


def open_udp():
    """A non-blocking UDP socket on a free loopback port, announced on stdout as `UDP
    PORT` (the first line the test reads)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.setblocking(False)
    print("UDP %d" % sock.getsockname()[1], flush=True)
    return sock


def udp_reply(sock):
    """(peer, send): `peer[0]` is the address last heard from, and send(b) answers it
    (nothing is sent before a first datagram)."""
    peer = [None]

    def send(b):
        if peer[0] is not None:
            sock.sendto(b, peer[0])

    return peer, send


def recv_udp(sock, peer):
    """A datagram that came within 5 ms, or b""; its sender becomes `peer[0]`."""
    r, _, _ = select.select([sock], [], [], 0.005)
    if not r:
        return b""
    data, addr = sock.recvfrom(4096)
    peer[0] = addr
    return data


def open_pty():
    """The master side of a new raw pseudo-terminal, non-blocking; the slave's path is
    announced on stdout as `PTY PATH` (the first line the test reads)."""
    import tty

    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    print("PTY %s" % os.ttyname(slave), flush=True)
    return master


def pty_write(master, b):
    """Writes `b` to the pseudo-terminal; a peer gone is not an error."""
    try:
        os.write(master, b)
    except OSError:
        pass


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--mode", choices=["udp", "pty", "tcp"], default="udp")
    ap.add_argument("--pilot", choices=["rc", "manual"], default="rc")
    ap.add_argument("--deadline", type=float, default=30.0)
    ap.add_argument("--scenario", choices=["interop", "pilot", "params", "thrust", "station",
                                           "takeover", "noplan", "exit", "hold"], default="interop")
    ap.add_argument("--pilot-mode-after", type=float, default=-1.0,
                    help="hold scenario: the pilot selects STABILIZE this long after 'markhold on'")
    ap.add_argument("--volts", type=float, default=16.0, help="thrust scenario: supply voltage")
    ap.add_argument("--param", action="append", default=[], help="NAME=VALUE override")
    ap.add_argument("--no-pilot-after-exit", action="store_true")
    ap.add_argument("--station", choices=["alive", "none"], default="alive",
                    help="the pilot's station (QGroundControl's heartbeat from 255/190)")
    ap.add_argument("--station-silent-after", type=float, default=1.0,
                    help="station scenario: seconds after markhold engaged")
    ap.add_argument("--takeover-after", type=float, default=1.0,
                    help="takeover scenario: seconds after markhold engaged")
    ap.add_argument("--ardusub", choices=["4.5", "4.2dev"], default="4.5",
                    help="whose rules for ground-station contact (see ArduSubInput)")
    args = ap.parse_args()
    if args.scenario == "thrust":
        return thrust_main(args)
    if args.scenario == "exit":
        return exit_main(args)
    if args.scenario == "hold":
        return hold_main(args)
    if args.scenario != "interop":
        return pilot_main(args)

    peer = [None]
    if args.mode == "udp":
        sock = open_udp()
        udp_peers = {}  # address -> its current Session
        udp_seqs = {}  # address -> {(system, component): last MAVLink sequence}
        peer, send = udp_reply(sock)

        def recv():
            return recv_udp(sock, peer)
    else:
        master = open_pty()

        def send(b):
            pty_write(master, b)

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
                # markhold is a component of this vehicle (system 1, component 191), an
                # onboard controller: a heartbeat from SYSID_MYGCS would keep ArduSub's
                # GCS failsafe quiet.
                gcs_hb_times.append(now)
                if m.type != mav2.MAV_TYPE_ONBOARD_CONTROLLER or m.autopilot != mav2.MAV_AUTOPILOT_INVALID:
                    failures.append("heartbeat type %d autopilot %d" % (m.type, m.autopilot))
                if src != (1, 191):
                    failures.append("heartbeat from %d/%d" % src)
            elif t in ("RC_CHANNELS_OVERRIDE", "MANUAL_CONTROL"):
                if src[0] != 255:
                    failures.append("%s from system %d (ArduSub drops it)" % (t, src[0]))
                pilot.append((now, t, m))
            elif t == "COMMAND_LONG":
                if src != (1, 191):
                    failures.append("COMMAND_LONG from %d/%d" % src)
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
# FS_GCS_TIMEOUT: ArduSub up to 4.5 has no parameter and waits a fixed 2.5 s
# (FS_GCS_TIMEOUT_MS, ArduSub/defines.h); later versions read it (default 5 s). This
# vehicle reports 2.5 s, to keep the runs short.
PARAMS = {
    "SYSID_MYGCS": 255.0,
    "FS_PILOT_INPUT": 2.0,
    "FS_PILOT_TIMEOUT": 3.0,
    "FS_GCS_ENABLE": 2.0,
    "FS_GCS_TIMEOUT": 2.5,
    "FRAME_CONFIG": 2.0,
    "RC_OVERRIDE_TIME": 3.0,
    "EK3_SRC1_POSXY": 6.0,
    "EK3_SRC1_VELXY": 6.0,
    "EK3_SRC1_YAW": 1.0,
    "VISO_TYPE": 1.0,
}
PILOT = (255, 190)  # QGroundControl
MARKHOLD_COMPID = 191
MANUAL, STABILIZE, ALT_HOLD_MODE, SURFACE = 19, 0, 2, 9
PILOT_TYPES = ("RC_CHANNELS_OVERRIDE", "MANUAL_CONTROL")
# Sub::failsafe_gcs_check runs in Sub::three_hz_loop (ArduSub/ArduSub.cpp).
GCS_CHECK_PERIOD_S = 1.0 / 3.3


class ArduSubInput:
    """ArduSub's pilot input and ground-station contact, written from its source
    (ArduSub 4.5: ArduSub/GCS_Mavlink.cpp, libraries/GCS_MAVLink/GCS_Common.cpp):

    - RC_CHANNELS_OVERRIDE is taken from SYSID_MYGCS only
      (GCS_MAVLINK::handle_rc_channels_override); 65535 leaves a channel alone, 0
      releases it, and with no RC receiver (a BlueROV2: RC_Channel::update returns
      without reading) a released channel keeps its last value;
    - MANUAL_CONTROL is taken from SYSID_MYGCS, aimed at the vehicle only, and turned
      into overrides (Sub::transform_manual_control_to_rc_override, joystick gain);
    - both are pilot input (failsafe.last_pilot_input_ms, FS_PILOT_INPUT) and, with any
      HEARTBEAT from SYSID_MYGCS whatever its type or component
      (GCS_MAVLINK::handle_heartbeat), ground-station contact (sysid_myggcs_seen), which
      Sub::failsafe_gcs_check times out after FS_GCS_TIMEOUT, at 3.3 Hz, when armed,
      once a GCS has been seen.

    `ardusub="4.2dev"` plays Blue Robotics' ArduSub V4.2.0dev (the SITL markhold flies,
    bluerobotics/ardupilot b6606a8f5d): there GCS_MAVLINK::handle_rc_channels_override
    is not ground-station contact; HEARTBEAT and MANUAL_CONTROL from SYSID_MYGCS are
    (GCS_MAVLINK_Sub::handleMessage sets failsafe.last_heartbeat_ms)."""

    def __init__(self, sysid_mygcs, sysid=1, gain=0.5, ardusub="4.5"):
        self.rc_is_contact = ardusub != "4.2dev"
        self.sysid_mygcs = sysid_mygcs
        self.sysid = sysid
        self.gain = gain
        self.ch = {i: 1500 for i in range(1, 9)}
        self.last_contact = None
        self.last_input = None
        self.applied = 0

    def contact(self, now):
        self.last_contact = now

    def manual_control(self, now, x, y, z, r, s=0, t=0, ext=0):
        rpy = 0.4 * self.gain
        thr = 0.8 * self.gain
        ax = lambda v: max(1100, min(1900, int(1500 + v * rpy)))
        self.ch[3] = max(1100, min(1900, int(1500 - 500 * thr + z * thr)))
        self.ch[4], self.ch[5], self.ch[6] = ax(r), ax(x), ax(y)
        if ext & 1:
            self.ch[1] = ax(s)
        if ext & 2:
            self.ch[2] = ax(t)
        self.last_input = now
        self.last_contact = now
        self.applied += 1

    def handle(self, m, now):
        """A frame from the link: True if it was applied as pilot input."""
        t = m.get_type()
        src = m.get_srcSystem()
        if t == "HEARTBEAT":
            if src == self.sysid_mygcs:
                self.contact(now)
            return False
        if src != self.sysid_mygcs:
            return False  # "Only accept control from our gcs"
        if t == "RC_CHANNELS_OVERRIDE":
            raw = [m.chan1_raw, m.chan2_raw, m.chan3_raw, m.chan4_raw,
                   m.chan5_raw, m.chan6_raw, m.chan7_raw, m.chan8_raw]
            for i, v in enumerate(raw):
                if v not in (0, 65535):
                    self.ch[i + 1] = v
            self.last_input = now
            if self.rc_is_contact:
                self.last_contact = now
            self.applied += 1
            return True
        if t == "MANUAL_CONTROL":
            if m.target != self.sysid:
                return False
            self.manual_control(now, m.x, m.y, m.z, m.r, m.s, m.t, m.enabled_extensions)
            return True
        return False

    def channels(self):
        return [self.ch[i] for i in range(1, 9)]

    def neutral(self):
        return all(self.ch[i] == 1500 for i in range(1, 7))


class GcsFailsafe:
    """Sub::failsafe_gcs_check (ArduSub/failsafe.cpp): FS_GCS_ENABLE 0 off, 1 warn, 2
    disarm, 3 depth hold, 4 surface; nothing until a GCS has been seen; only armed."""

    def __init__(self, params):
        self.enable = int(params.get("FS_GCS_ENABLE", 0))
        self.timeout = params.get("FS_GCS_TIMEOUT", 2.5)
        self.next_check = 0.0
        self.active = False
        self.fired = []

    def check(self, now, inp, st):
        """At 3.3 Hz; returns the action taken, if any."""
        if now < self.next_check:
            return None
        self.next_check = now + GCS_CHECK_PERIOD_S
        if self.enable == 0 or inp.last_contact is None:
            return None
        if now - inp.last_contact < self.timeout:
            self.active = False
            return None
        if self.active or not st["armed"]:
            return None
        self.active = True
        self.fired.append(now)
        if self.enable == 2:
            st["armed"] = False
        elif self.enable == 3:
            st["mode"] = ALT_HOLD_MODE
        elif self.enable == 4:
            st["mode"] = SURFACE
        st["hb_now"] = True
        return self.enable


def pilot_main(args):
    """An ArduSub vehicle with the pilot's station beside it (QGroundControl as 255/190,
    its packets reaching markhold through the router: the vehicle hears them too).
    Scenarios: `pilot` (the plan of step_plan), `params` (heartbeats and parameters
    only), `station` (the station falls silent `--station-silent-after` s after markhold
    engaged), `takeover` (the pilot switches to STABILIZE `--takeover-after` s after
    markhold engaged and stays), `noplan` (the pilot does nothing). `--station none`: no
    station at all. Ends 1.5 s after markhold falls silent."""
    params = dict(PARAMS)
    for kv in args.param:
        k, v = kv.split("=", 1)
        params[k] = float(v)
    names = sorted(params)
    sock = open_udp()
    peer, send = udp_reply(sock)

    veh = mav2.MAVLink(Out(send), srcSystem=1, srcComponent=1)
    veh.robust_parsing = True
    # The pilot's QGroundControl: its packets reach markhold through the router.
    qgc = mav2.MAVLink(Out(send), srcSystem=PILOT[0], srcComponent=PILOT[1])
    sysid_mygcs = int(params["SYSID_MYGCS"])
    inp = ArduSubInput(sysid_mygcs, ardusub=args.ardusub)
    gcs_fs = GcsFailsafe(params)

    failures = []
    st = {"armed": False, "mode": MANUAL if args.scenario != "params" else STABILIZE}
    texts = []  # (t, severity, text) from markhold
    log = []  # (t, event)
    mh_inputs = []  # (t, kind) kind: "cmd" (non-neutral), "neutral", "release"
    # markhold's pilot input and STATUSTEXT in arrival order (the order it sent them):
    # (t, "input", kind) or (t, "text", text).
    mh_seq = []
    mh_ids = set()  # (sysid, compid, type) of every frame markhold sent
    gcs_frames = []  # t of every frame markhold sent as SYSID_MYGCS
    streams = set()
    failsafe = []
    param_reads = [0]
    named = set()
    t0 = time.time()
    last_hb = 0.0
    last_js = 0.0
    last_station_hb = [None]
    station = {"on": args.station != "none"}
    last_heard = [None]
    # The pilot's plan, driven by what markhold says.
    plan = {"step": 0, "at": None, "deflect_until": None, "js": args.scenario == "pilot",
            "no_js_after_exit": args.no_pilot_after_exit}
    change_t = [None]

    def rel(t):
        return round(t - t0, 3)

    def pilot_mode(m):
        now = time.time()
        log.append((rel(now), "pilot mode %d" % m))
        # COMMAND_LONG from QGroundControl: the vehicle switches; the router shows it to
        # markhold too.
        qgc.command_long_send(1, 1, mav2.MAV_CMD_DO_SET_MODE, 0, 1, m, 0, 0, 0, 0, 0)
        st["mode"] = m
        st["hb_now"] = True
        change_t[0] = now

    def pilot_arm():
        log.append((rel(time.time()), "pilot arm"))
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
            critical = now < st.get("critical_until", 0) or gcs_fs.active
            status = mav2.MAV_STATE_CRITICAL if critical else mav2.MAV_STATE_ACTIVE
            veh.heartbeat_send(mav2.MAV_TYPE_SUBMARINE, mav2.MAV_AUTOPILOT_ARDUPILOTMEGA, base, st["mode"], status)
            veh.attitude_send(1234, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
            # A still vehicle 1 m deep (hil --vehicle renders its camera from these).
            veh.local_position_ned_send(1234, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
            if 65 in streams:
                veh.rc_channels_send(1234, 8, *(inp.channels() + [0] * 10), 255)
        # The pilot's station: QGroundControl heartbeats at 1 Hz (MAV_TYPE_GCS).
        if station["on"] and peer[0] is not None and (last_station_hb[0] is None or now - last_station_hb[0] >= 1.0):
            last_station_hb[0] = now
            qgc.heartbeat_send(mav2.MAV_TYPE_GCS, mav2.MAV_AUTOPILOT_INVALID, 0, 0, mav2.MAV_STATE_ACTIVE)
            inp.contact(now)
        # The pilot's joystick: QGroundControl sends MANUAL_CONTROL all the time, centred
        # unless the pilot deflects it.
        if plan["js"] and station["on"] and st["armed"] and now - last_js >= 0.05:
            last_js = now
            x = 600 if plan["deflect_until"] and now < plan["deflect_until"] else 0
            qgc.manual_control_send(1, x, 0, 500, 0, 0)
            if PILOT[0] == sysid_mygcs:
                inp.manual_control(now, x, 0, 500, 0)
        # The pilot-input failsafe (FS_PILOT_INPUT), as ArduSub runs it.
        if st["armed"] and params["FS_PILOT_INPUT"] != 0 and inp.last_input is not None:
            if now - inp.last_input > params["FS_PILOT_TIMEOUT"]:
                failsafe.append(rel(now))
                veh.statustext_send(mav2.MAV_SEVERITY_CRITICAL, b"Lost manual control")
                st["armed"] = False
        # The GCS failsafe (FS_GCS_ENABLE), as ArduSub runs it.
        if gcs_fs.check(now, inp, st) is not None:
            log.append((rel(now), "gcs failsafe"))
            veh.statustext_send(mav2.MAV_SEVERITY_WARNING, b"MYGCS: %d, heartbeat lost" % sysid_mygcs)
        if args.scenario == "pilot":
            step_plan(plan, now, said, pilot_mode, pilot_arm, mh_inputs, mh_seq, change_t, failures)
            if plan.pop("vehicle_text", False):
                # What ArduSub says on a leak: markhold must log it.
                veh.statustext_send(mav2.MAV_SEVERITY_CRITICAL, b"Leak Detected!")
                st["critical_until"] = now + 0.3
        elif args.scenario in ("station", "takeover", "noplan"):
            if plan["step"] == 0 and said("markhold ready"):
                pilot_arm()
                plan["step"] = 1
            if plan["step"] <= 1 and said("markhold on"):
                plan["step"], plan["at"] = 2, now
            if plan["step"] == 2 and args.scenario == "station" and now - plan["at"] >= args.station_silent_after:
                station["on"] = False
                log.append((rel(now), "station silent"))
                plan["step"] = 3
            if plan["step"] == 2 and args.scenario == "takeover" and now - plan["at"] >= args.takeover_after:
                # The pilot switches mode and flies on with the joystick.
                pilot_mode(STABILIZE)
                plan["js"] = True
                plan["step"] = 3
        data = recv_udp(sock, peer)
        if not data:
            if last_heard[0] is not None and now - last_heard[0] > 1.5:
                break
            continue
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
            mh_ids.add((src[0], src[1], t))
            if src[0] == sysid_mygcs:
                gcs_frames.append(rel(now))
            inp.handle(m, now)
            if t == "STATUSTEXT":
                text = m.text if isinstance(m.text, str) else m.text.decode()
                texts.append((rel(now), m.severity, text))
                mh_seq.append((now, "text", text))
                if len(text.encode()) >= 50:
                    failures.append("statustext of %d bytes" % len(text.encode()))
            elif t == "NAMED_VALUE_FLOAT":
                named.add(m.name if isinstance(m.name, str) else m.name.decode())
            elif t == "RC_CHANNELS_OVERRIDE":
                ch = [m.chan1_raw, m.chan2_raw, m.chan3_raw, m.chan4_raw, m.chan5_raw, m.chan6_raw]
                kind = "release" if ch == [0] * 6 else ("neutral" if ch == [1500] * 6 else "cmd")
                mh_inputs.append((now, kind))
                mh_seq.append((now, "input", kind))
            elif t == "MANUAL_CONTROL":
                kind = "neutral" if (m.x, m.y, m.z, m.r) == (0, 0, 500, 0) else "cmd"
                mh_inputs.append((now, kind))
                mh_seq.append((now, "input", kind))
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
                    log.append((rel(now), "markhold arm %d" % st["armed"]))
                elif m.command == mav2.MAV_CMD_DO_SET_MODE:
                    st["mode"] = int(m.param2)
                    st["hb_now"] = True
                    log.append((rel(now), "markhold mode %d" % st["mode"]))
                elif m.command == mav2.MAV_CMD_SET_MESSAGE_INTERVAL:
                    streams.add(int(m.param1))
                elif m.command == mav2.MAV_CMD_REQUEST_MESSAGE and int(m.param1) == 148:
                    veh.autopilot_version_send(0, (4 << 24) | (1 << 16) | (2 << 8) | 255, 0, 0, 0,
                                               [0] * 8, [0] * 8, [0] * 8, 0, 0, 0)
                veh.command_ack_send(m.command, result)

    after = None
    around = None
    if change_t[0] is not None:
        after = [k for t, k in mh_inputs if t > change_t[0]]
        around = around_text(mh_seq, change_t[0], "markhold off: mode changed")
    verdict = {
        "ok": not failures,
        "failures": failures[:20],
        "texts": texts,
        "log": log,
        "failsafe": failsafe,
        "gcs_failsafe": [rel(t) for t in gcs_fs.fired],
        "fs_gcs_timeout_s": gcs_fs.timeout,
        "station_last_hb": rel(last_station_hb[0]) if last_station_hb[0] is not None else None,
        "gcs_frames": gcs_frames,
        "mh_ids": sorted(mh_ids),
        "armed_at_end": st["armed"],
        "mode_at_end": st["mode"],
        "param_reads": param_reads[0],
        "named": sorted(named),
        "step": plan["step"],
        "inputs_after_mode_change": plan.get("after_change", after),
        "inputs_after_change_to_end": after,
        "around_off_text": plan.get("around", around),
        "inputs_while_off": plan.get("while_off"),
        "release_seen": plan.get("release"),
        "last_input_after_mode_change_ms": plan.get("last_input_ms"),
        "applied_at_end": inp.channels(),
    }
    print(json.dumps(verdict), flush=True)
    sys.exit(0 if not failures else 1)


def around_text(seq, since, prefix):
    """markhold's pilot input around its first STATUSTEXT starting with `prefix` after
    `since`: the last input before it and every input after it (None if not said). It
    says why it let go right after its neutral input, so by the order it sent them,
    whatever a loaded host does to the clocks: neutral, the text, then the release."""
    i = next((i for i, (t, k, x) in enumerate(seq) if t > since and k == "text" and x.startswith(prefix)), None)
    if i is None:
        return None
    before = [x for _, k, x in seq[:i] if k == "input"]
    return {"before": before[-1] if before else None,
            "after": [x for _, k, x in seq[i + 1:] if k == "input"]}


def step_plan(plan, now, said, pilot_mode, pilot_arm, mh_inputs, mh_seq, change_t, failures):
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
        # Judged by order, not by the wall clock (a loaded host delays everything): when
        # markhold hears the change it sends one neutral and says why, and after that
        # nothing but the release. (What it sent before hearing it was in flight;
        # last_input_ms reports the wall-clock figure.)
        plan["around"] = around = around_text(mh_seq, change_t[0], "markhold off: mode changed")
        if around is None:
            failures.append("no 'markhold off: mode changed'")
        elif around["before"] != "neutral" or around["after"] != ["release"]:
            failures.append("pilot input around 'markhold off: mode changed': %r" % (around,))
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


def exit_main(args):
    """An ArduSub vehicle for markhold's exit (`--scenario exit`), over UDP, TCP (a
    server that takes one connection after another, as SITL does) or a pseudo-terminal.
    It applies pilot input as ArduSub does (ArduSubInput), streams RC_CHANNELS and
    SERVO_OUTPUT_RAW at the intervals asked for (motor outputs follow the sticks as in
    MANUAL), answers arm, mode and parameter reads. Every link session (a UDP peer, a
    TCP connection, or on the pseudo-terminal the value of markhold's NAMED_VALUE_FLOAT
    `mh_sess`) keeps its own record: the input applied when it ended. The first input a
    session applies off neutral prints "CMD <session>". Ends when stdin closes (or at
    the deadline) with the verdict: every session and its last applied input."""
    params = dict(PARAMS)
    names = sorted(params)
    sysid_mygcs = int(params["SYSID_MYGCS"])
    sessions = {}
    order = []

    class Session:
        def __init__(self, key, send):
            self.key = key
            self.veh = mav2.MAVLink(Out(send), srcSystem=1, srcComponent=1)
            self.veh.robust_parsing = True
            self.inp = ArduSubInput(sysid_mygcs)
            self.intervals = {}  # msg id -> (period s, next due)
            self.cmd_applied = 0
            self.armed = False
            self.mode = MANUAL
            self.end = None
            self.last_hb = 0.0
            self.texts = []
            self.mh_sess = None
            self.final = None
            sessions[key] = self
            order.append(key)

        def follow(self, prev):
            """The same vehicle, a new markhold on the same line: its state goes on."""
            self.inp.ch = dict(prev.inp.ch)
            self.intervals = prev.intervals
            self.armed, self.mode = prev.armed, prev.mode
            prev.end = "next"
            prev.final = prev.record()

        def record(self):
            if self.final is not None:
                return self.final
            return {"key": str(self.key), "mh_sess": self.mh_sess,
                    "applied": self.inp.channels()[:6], "neutral": self.inp.neutral(),
                    "cmd_applied": self.cmd_applied, "inputs": self.inp.applied,
                    "end": self.end, "texts": self.texts, "armed": self.armed}

        def tick(self, now):
            v = self.veh
            if now - self.last_hb >= 0.1:
                self.last_hb = now
                base = mav2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mav2.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0)
                v.heartbeat_send(mav2.MAV_TYPE_SUBMARINE, mav2.MAV_AUTOPILOT_ARDUPILOTMEGA, base, self.mode, mav2.MAV_STATE_ACTIVE)
            for mid, (period, due) in list(self.intervals.items()):
                if now < due:
                    continue
                self.intervals[mid] = (period, now + period)
                ch = self.inp.channels()
                if mid == 65:
                    v.rc_channels_send(1234, 8, *(ch + [0] * 10), 255)
                elif mid == 36:
                    # A stand-in for MANUAL: the thrusters are off neutral exactly when
                    # a stick is.
                    v.servo_output_raw_send(1234, 0, *ch[:8])
                elif mid == 30:
                    v.attitude_send(1234, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

        def frame(self, m, now):
            t = m.get_type()
            if t == "BAD_DATA":
                return
            if t == "NAMED_VALUE_FLOAT":
                name = m.name if isinstance(m.name, str) else m.name.decode()
                if name == "mh_sess":
                    return "mh_sess", int(m.value)
            applied = self.inp.handle(m, now)
            if applied and not self.inp.neutral():
                if self.cmd_applied == 0:
                    print("CMD %s" % (self.mh_sess if self.mh_sess is not None else str(self.key)), flush=True)
                self.cmd_applied += 1
            v = self.veh
            if t == "STATUSTEXT":
                self.texts.append(m.text if isinstance(m.text, str) else m.text.decode())
            elif t == "PARAM_REQUEST_READ":
                pid = m.param_id if isinstance(m.param_id, str) else m.param_id.decode()
                if pid in params:
                    v.param_value_send(pid.encode(), params[pid], mav2.MAV_PARAM_TYPE_REAL32, len(names), names.index(pid))
            elif t == "COMMAND_LONG":
                if m.command == mav2.MAV_CMD_COMPONENT_ARM_DISARM:
                    self.armed = m.param1 > 0.5
                elif m.command == mav2.MAV_CMD_DO_SET_MODE:
                    self.mode = int(m.param2)
                elif m.command == mav2.MAV_CMD_SET_MESSAGE_INTERVAL and m.param2 > 0:
                    self.intervals[int(m.param1)] = (m.param2 / 1e6, now)
                v.command_ack_send(m.command, mav2.MAV_RESULT_ACCEPTED)
            return None

    t0 = time.time()
    stdin = sys.stdin.fileno()
    os.set_blocking(stdin, False)
    watch = [stdin]
    done = False
    if args.mode == "udp":
        sock = open_udp()
        udp_peers = {}  # address -> its current Session
        udp_seqs = {}  # address -> {(system, component): last MAVLink sequence}
        watch.append(sock)
    elif args.mode == "tcp":
        lsock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        lsock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        lsock.bind(("127.0.0.1", 0))
        lsock.listen(4)
        lsock.setblocking(False)
        print("TCP %d" % lsock.getsockname()[1], flush=True)
        watch.append(lsock)
        conns = {}  # socket -> Session
        n_conn = [0]
    else:
        master = open_pty()
        watch.append(master)

        def pty_send(b):
            pty_write(master, b)
        pty_session = [Session("pty-0", pty_send)]
        pty_parser = mav2.MAVLink(Out(lambda b: None), srcSystem=1, srcComponent=1)
        pty_parser.robust_parsing = True

    while not done and time.time() - t0 < args.deadline:
        now = time.time()
        for sess in list(sessions.values()):
            if sess.end is None:
                sess.tick(now)
        r, _, _ = select.select(watch, [], [], 0.002)
        for f in r:
            if f == stdin:
                try:
                    if os.read(stdin, 4096) == b"":
                        done = True
                except BlockingIOError:
                    pass
            elif args.mode == "udp":
                data, addr = sock.recvfrom(65536)
                sess = udp_peers.get(addr)
                if sess is None:
                    sess = Session(addr, lambda b, a=addr: sock.sendto(b, a))
                    udp_peers[addr] = sess
                for m in sess.veh.parse_buffer(data) or []:
                    # A markhold starts each of its MAVLink sequences at 0: a sequence
                    # that restarts (not a wrap) is a later markhold the kernel gave an
                    # earlier one's UDP port, a new session of the same vehicle.
                    if m.get_type() != "BAD_DATA":
                        sid = (m.get_srcSystem(), m.get_srcComponent())
                        seqs = udp_seqs.setdefault(addr, {})
                        last = seqs.get(sid)
                        if m.get_seq() == 0 and last is not None and last != 255:
                            new = Session((addr, len(sessions)), lambda b, a=addr: sock.sendto(b, a))
                            new.follow(sess)
                            udp_peers[addr] = sess = new
                            seqs.clear()
                        seqs[sid] = m.get_seq()
                    got = sess.frame(m, now)
                    if got:
                        if sess.mh_sess is not None and got[1] != sess.mh_sess:
                            # The kernel gave a later markhold the port of an earlier
                            # one: a new session of the same vehicle.
                            new = Session((addr, got[1]), lambda b, a=addr: sock.sendto(b, a))
                            new.follow(sess)
                            udp_peers[addr] = sess = new
                        sess.mh_sess = got[1]
            elif args.mode == "tcp":
                if f == lsock:
                    c, _ = lsock.accept()
                    c.setblocking(False)
                    n_conn[0] += 1

                    def tsend(b, c=c):
                        try:
                            c.sendall(b)
                        except OSError:
                            pass
                    conns[c] = Session("tcp-%d" % n_conn[0], tsend)
                    watch.append(c)
                    continue
                sess = conns[f]
                try:
                    data = f.recv(65536)
                except ConnectionResetError:
                    data = None
                if not data:
                    # The end of markhold's stream (or a reset): close ours, as SITL does.
                    sess.end = "eof" if data == b"" else "reset"
                    watch.remove(f)
                    f.close()
                    continue
                for m in sess.veh.parse_buffer(data) or []:
                    got = sess.frame(m, now)
                    if got:
                        sess.mh_sess = got[1]
            else:
                try:
                    data = os.read(master, 65536)
                except OSError:
                    time.sleep(0.002)
                    continue
                sess = pty_session[0]
                for m in pty_parser.parse_buffer(data) or []:
                    got = sess.frame(m, now)
                    if got and got[0] == "mh_sess" and got[1] != sess.mh_sess:
                        # markhold's next session on the same device.
                        if sess.mh_sess is not None:
                            prev = sess
                            sess = Session("pty-%d" % got[1], pty_send)
                            sess.follow(prev)
                            pty_session[0] = sess
                        sess.mh_sess = got[1]
                        print("SESSION %d" % got[1], flush=True)
    verdict = {"sessions": [sessions[k].record() for k in order]}
    print(json.dumps(verdict), flush=True)


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
    sock = open_udp()
    peer, send = udp_reply(sock)

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
        data = recv_udp(sock, peer)
        if not data:
            if last_heard is not None and now - last_heard > 1.0:
                break
            continue
        last_heard = now
        for m in veh.parse_buffer(data) or []:
            t = m.get_type()
            if t in PILOT_TYPES and m.get_srcSystem() != 255:
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
    sock = open_udp()
    peer, send = udp_reply(sock)

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
        data = recv_udp(sock, peer)
        if not data:
            if last_heard is not None and now - last_heard > 1.5:
                break
            continue
        last_heard = now
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
            elif t in ("RC_CHANNELS_OVERRIDE", "MANUAL_CONTROL") and m.get_srcSystem() != 255:
                # ArduSub takes pilot input from SYSID_MYGCS alone; commands from anyone.
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
