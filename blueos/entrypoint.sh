#!/bin/sh
# The BlueOS extension's entry point: check the vehicle, then hold station when the
# pilot engages from QGroundControl (markhold never engages by itself here). The page
# (status, camera, site file, recording) is on port 8780: BlueOS lists it in its sidebar.
#   MARKHOLD_SITE    site file (default /data/site.toml, i.e. the host's
#                    /usr/blueos/extensions/markhold/site.toml)
#   MARKHOLD_CAMERA  camera URL (default udp:127.0.0.1:5610: a UDP endpoint added to the
#                    camera manager's stream; never the camera's /dev/video device, which
#                    the camera manager streams)
#   MARKHOLD_LINK    MAVLink URL (default tcp:127.0.0.1:5777, BlueOS's MAVLink router)
#   MARKHOLD_WEB     the page's address (default 0.0.0.0:8780; empty: no page)
#   MARKHOLD_FOXGLOVE_PORT  the Foxglove live view's port on every address (default
#                    8765; empty: no live view)
#   MARKHOLD_ARGS    more `markhold run` options
set -u
site="${MARKHOLD_SITE:-/data/site.toml}"
camera="${MARKHOLD_CAMERA:-udp:127.0.0.1:5610}"
link="${MARKHOLD_LINK:-tcp:127.0.0.1:5777}"
web="${MARKHOLD_WEB-0.0.0.0:8780}"
live_port="${MARKHOLD_FOXGLOVE_PORT-8765}"
rec_dir="/data/recordings"

if [ ! -f "$site" ]; then
  echo "markhold: no site file at $site: copy one of /usr/share/markhold/params/*.toml to" \
       "/usr/blueos/extensions/markhold/site.toml on the vehicle and restart the extension" >&2
  # Stay up so the message shows in the extension's log instead of a restart loop.
  exec sleep infinity
fi
mkdir -p "$rec_dir"
set --
if [ -n "$web" ]; then
  set -- "$@" --web "$web"
fi
if [ -n "$live_port" ]; then
  set -- "$@" --foxglove --foxglove-port "$live_port" --foxglove-bind 0.0.0.0
fi
while true; do
  if markhold preflight --site "$site" --link "$link"; then
    # Segments, quota and free-space floor: the site's [record.rotation].
    rec="$rec_dir/markhold-$(date -u +%Y%m%dT%H%M%SZ).mcap"
    # The checklist just passed: run without repeating it. ${MARKHOLD_ARGS} is split on
    # purpose (several options).
    # shellcheck disable=SC2086
    markhold run --no-preflight --site "$site" --camera "$camera" --link "$link" \
      --record "$rec" "$@" ${MARKHOLD_ARGS:-}
    echo "markhold: run ended ($?); starting again in 5 s" >&2
  else
    echo "markhold: preflight did not pass; checking again in 30 s (fix the items above)" >&2
    sleep 25
  fi
  sleep 5
done
