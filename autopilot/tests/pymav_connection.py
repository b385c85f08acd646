#!/usr/bin/env python3
"""A pymavlink peer opened with pymavlink's own connection string, for markhold-autopilot's
connection-string test.

It opens `mavutil.mavlink_connection(URL)` as system 1 (an ArduSub-like vehicle), prints
its local UDP port on the first stdout line ("PORT <port>"), sends a heartbeat every 0.1 s
(a listening connection sends only once a peer has spoken) and waits for markhold's
heartbeat (system 1, component 191: a component of this vehicle), then goes on for 0.5 s so that markhold hears it too (a
listening pymavlink sends to the peers it has heard). The verdict is a JSON line on stdout and the exit status
(0 = markhold's heartbeat arrived before the deadline).
"""
import argparse
import json
import os
import sys
import time

os.environ["MAVLINK20"] = "1"  # MAVLink 2 on the wire, as markhold speaks it
from pymavlink import mavutil  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--url", required=True)
    ap.add_argument("--deadline", type=float, default=15.0)
    args = ap.parse_args()

    conn = mavutil.mavlink_connection(args.url, source_system=1, source_component=1)
    print("PORT %d" % conn.port.getsockname()[1], flush=True)
    m = conn.mav
    t0 = time.time()
    last_hb = 0.0
    gcs = 0
    first_gcs = None
    while time.time() - t0 < args.deadline:
        now = time.time()
        if first_gcs is not None and now - first_gcs > 0.5:
            break
        if now - last_hb >= 0.1:
            last_hb = now
            m.heartbeat_send(
                mavutil.mavlink.MAV_TYPE_SUBMARINE,
                mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                19,
                mavutil.mavlink.MAV_STATE_ACTIVE,
            )
        msg = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=0.05)
        if msg is not None and (msg.get_srcSystem(), msg.get_srcComponent()) == (1, 191):
            gcs += 1
            if first_gcs is None:
                first_gcs = time.time()
    verdict = {
        "ok": gcs > 0,
        "url": args.url,
        "udp_server": bool(getattr(conn, "udp_server", False)),
        "markhold_heartbeats": gcs,
    }
    print(json.dumps(verdict), flush=True)
    sys.exit(0 if gcs > 0 else 1)


if __name__ == "__main__":
    main()
