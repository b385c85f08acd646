// markhold's page: polls status.json, reloads the camera view, shows the site file with
// its check in place. Every URL is relative (the page also lives behind BlueOS's proxy).
'use strict';

const $ = (id) => document.getElementById(id);
const widget = new URLSearchParams(location.search).get('view') === 'widget';
if (widget) document.body.classList.add('widget');

const seen = { first: null, updates: 0, frames: 0 };
let snapshotMs = 200;

function num(v, digits) {
  return v === null || v === undefined || !Number.isFinite(Number(v)) ? '-' : Number(v).toFixed(digits);
}

function show(id, text, cls) {
  const el = $(id);
  el.textContent = text;
  el.className = cls || '';
}

const ENGAGEMENT = {
  always: ['commanding whenever the failsafes allow (no pilot engagement in this runner)', 'good'],
  waiting: ['waiting for the vehicle', 'warn'],
  ready: ['ready: the pilot engages by arming in the site\'s mode (or switching to it armed)', ''],
  engaged: ['ENGAGED: holding station', 'good'],
  releasing: ['letting go: neutral, then the controls back to the pilot', 'warn'],
  pending: ['engage asked: waiting to hear the pilot station', 'warn'],
};

function eventName(ev) {
  if (!ev) return '';
  const kind = Object.keys(ev)[0];
  const at = ev[kind] && ev[kind].at_s;
  return kind.replace(/([a-z])([A-Z])/g, '$1 $2').toLowerCase() + (at !== undefined ? ` at ${num(at, 1)} s` : '');
}

function render(j) {
  const s = j.status;
  seen.updates += 1;
  if (seen.first === null && s.frames > 0) seen.first = s.seq;
  document.body.dataset.statusUpdates = seen.updates;
  document.body.dataset.firstSeq = seen.first === null ? '' : seen.first;
  document.body.dataset.lastSeq = s.frames > 0 ? s.seq : '';
  $('site-name').textContent = `${j.site} (${j.runner}, markhold ${j.version})`;
  if (j.snapshot_hz > 0) snapshotMs = Math.max(33, 1000 / j.snapshot_hz);

  const [etext, ecls] = ENGAGEMENT[s.engagement] || [s.engagement, ''];
  show('s-engagement', etext, ecls);

  const m = s.marker;
  if (m.detected) {
    show('s-marker', `seen: ${m.markers_used} marker(s) in the pose, reprojection ${num(m.reproj_rms_px, 2)} px`, 'good');
  } else if (m.seen_s !== null) {
    show('s-marker', `not seen for ${num(s.stamp_s - m.seen_s, 1)} s`, 'warn');
  } else {
    show('s-marker', 'not seen yet', 'warn');
  }

  const p = s.position;
  show('s-position', p
    ? `${num(p.distance_m, 3)} m (forward ${num(p.xyz_m[0], 3)}, right ${num(p.xyz_m[1], 3)}, down ${num(p.xyz_m[2], 3)}), yaw ${num(p.yaw_deg, 1)} deg`
    : 'no pose on this frame');

  const e = s.exposure;
  show('s-exposure', `${num(e.used_us, 0)} us, next ${num(e.next_us, 0)} us, gain ${num(e.gain_db, 1)} dB` +
    (e.metric !== null ? `, metric ${num(e.metric, 3)}` : ''));

  const l = s.link;
  if (!l) {
    show('s-link', 'no vehicle link');
  } else {
    const parts = [l.heard ? 'vehicle heard' : 'VEHICLE NOT HEARD', l.armed ? 'armed' : 'disarmed',
      `mode ${l.mode || '?'}`, `system ${l.system_id}`, `sent ${l.sent}, received ${l.received}`];
    show('s-link', parts.join(', '), l.heard ? 'good' : 'bad');
  }

  const f = s.failsafe;
  const active = [];
  if (f.vehicle_lost) active.push('vehicle lost');
  if (f.vision_stalled) active.push('camera stalled');
  if (f.marker_lost) active.push('marker lost');
  if (f.shutting_down) active.push('stopping');
  if (l && l.vehicle_failsafe) active.push('ArduSub failsafe active');
  const last = f.last ? ` (last: ${eventName(f.last)})` : '';
  show('s-failsafe', (active.length ? active.join(', ') : 'none') + last, active.length ? 'bad' : 'good');

  const stale = j.stale_s !== null && j.stale_s > 2;
  show('s-frame', s.frames > 0
    ? `frame ${s.seq} at ${num(s.stamp_s, 2)} s, ${s.frames} frames, ${s.directive}` +
      (stale ? `; no new frame for ${num(j.stale_s, 0)} s` : '')
    : 'no frame yet', stale ? 'bad' : '');

  const r = j.recording;
  if (!r) {
    show('r-state', 'this run does not record to a file (markhold run --record FILE.mcap)');
  } else {
    const where = r.segment ? ` ${r.segment}` : '';
    let text = r.recording
      ? `recording to${where}: ${num(r.segment_bytes / 1e6, 1)} MB, segment ${r.segments}`
      : `stopped${r.segment ? ` (last segment${where})` : ''}`;
    if (r.free_bytes !== null) text += `; ${num(r.free_bytes / 1e6, 0)} MB free`;
    if (r.deleted > 0) text += `; ${r.deleted} old recording(s) deleted for space`;
    if (r.stopped) text += `. ${r.stopped}`;
    show('r-state', text, r.stopped ? 'bad' : (r.recording ? 'good' : ''));
  }
  $('r-start').disabled = !r || r.recording;
  $('r-stop').disabled = !r || !r.recording;

  if (!j.live) {
    show('live', 'off (markhold run --foxglove)');
  } else {
    const url = `ws://${location.hostname}:${j.live.port}`;
    show('live', j.live.loopback
      ? `on ${url.replace(location.hostname, '127.0.0.1')}, loopback only (the topside cannot reach it: --foxglove-bind 0.0.0.0)`
      : `${url}: open it in Foxglove (desktop app: Open connection, Foxglove WebSocket). ` +
        'A browser page may connect only from an origin in the site\'s [live] allowed_origins.');
  }
}

async function pollStatus() {
  try {
    const r = await fetch('status.json', { cache: 'no-store' });
    if (!r.ok) throw new Error(`status ${r.status}`);
    render(await r.json());
    show('conn', 'connected', 'pill ok');
  } catch (err) {
    show('conn', 'markhold not answering', 'pill bad');
  }
  setTimeout(pollStatus, 500);
}

function nextFrame() {
  $('camera').src = `snapshot.jpg?t=${Date.now()}`;
}

$('camera').addEventListener('load', () => {
  const img = $('camera');
  seen.frames += 1;
  img.dataset.framesShown = seen.frames;
  img.dataset.width = img.naturalWidth;
  img.dataset.height = img.naturalHeight;
  $('camera-caption').textContent = `${img.naturalWidth} x ${img.naturalHeight}; marker outline green, metered region yellow`;
  setTimeout(nextFrame, snapshotMs);
});
$('camera').addEventListener('error', () => {
  $('camera-caption').textContent = 'no camera frame yet';
  setTimeout(nextFrame, 1000);
});

async function record(action) {
  try {
    const r = await fetch(`record/${action}`, { method: 'POST' });
    if (!r.ok) show('r-state', await r.text(), 'bad');
  } catch (err) {
    show('r-state', `markhold did not answer: ${err}`, 'bad');
  }
}
$('r-start').addEventListener('click', () => record('start'));
$('r-stop').addEventListener('click', () => record('stop'));

// The site file, one line per row; each error below its line, its key and message.
function renderSite(text, check, note) {
  const view = $('site-view');
  view.replaceChildren();
  const byLine = new Map();
  const placeless = [];
  for (const e of check.errors) {
    if (e.line) byLine.set(e.line, (byLine.get(e.line) || []).concat([e])); else placeless.push(e);
  }
  const errorBox = (e) => {
    const d = document.createElement('div');
    d.className = 'site-error';
    d.dataset.line = e.line || '';
    d.dataset.key = e.key;
    // The message names the file, line and column, the key and the value, as
    // `markhold params check` prints it.
    d.textContent = e.message;
    return d;
  };
  placeless.forEach((e) => view.appendChild(errorBox(e)));
  text.split('\n').forEach((line, i) => {
    const row = document.createElement('div');
    row.className = byLine.has(i + 1) ? 'line error' : 'line';
    const no = document.createElement('span');
    no.className = 'no';
    no.textContent = String(i + 1);
    const src = document.createElement('span');
    src.textContent = line;
    row.append(no, src);
    view.appendChild(row);
    (byLine.get(i + 1) || []).forEach((e) => view.appendChild(errorBox(e)));
  });
  const panel = $('site-panel');
  panel.dataset.ok = check.ok;
  show('site-summary', check.ok
    ? `passes the check${note ? ` (${note})` : ''}`
    : `${check.errors.length} error(s)${note ? ` (${note})` : ''}: fix them before markhold starts again`,
  check.ok ? 'good' : 'bad');
}

let siteDirty = false;
async function loadSite() {
  try {
    const r = await fetch('site.json', { cache: 'no-store' });
    const j = await r.json();
    $('site-path').textContent = j.path;
    if (!siteDirty) {
      renderSite(j.text, j.check, 'the file as saved');
      $('site-text').value = j.text;
    }
  } catch (err) {
    show('site-summary', `cannot read the site file: ${err}`, 'bad');
  }
}
$('site-text').addEventListener('input', () => { siteDirty = true; });

async function sendSite(path) {
  const text = $('site-text').value;
  const r = await fetch(path, { method: 'POST', body: text, headers: { 'Content-Type': 'text/plain' } });
  if (r.status !== 200 && r.status !== 422) {
    show('site-note', await r.text(), 'bad');
    return;
  }
  const check = await r.json();
  const saved = path === 'site' && r.status === 200;
  renderSite(text, check, saved ? 'saved' : 'checked, not saved');
  show('site-note', saved
    ? 'Saved. markhold uses it when it starts again (BlueOS: restart the extension).'
    : (check.ok ? 'Passes the check.' : 'Not saved: fix the errors shown.'), check.ok ? 'good' : 'bad');
  if (saved) siteDirty = false;
}
$('site-check').addEventListener('click', () => sendSite('site/check'));
$('site-save').addEventListener('click', () => sendSite('site'));

pollStatus();
nextFrame();
if (!widget) {
  loadSite();
  setInterval(loadSite, 5000);
}
