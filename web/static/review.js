// Review page: the private continuous video synchronised with the calls, private stage events, telemetry plots,
// the observation the agent received at each call and what the agent read, thought and ran before it (its
// transcript, /api/episodes/{id}/agent). ←/→ step one control step, space plays or pauses, ?t=seconds opens a moment.
// Without the video (an episode run without one, or one not rendered yet) each moment is rendered on demand from
// the recorded state (/api/episodes/{id}/moment?step=N) by a player with the video element's interface.
import { el, fmtS, callSummary, stageText, stageLabel, agentEventItem, agentEventText, showBlob } from './common.js';

const root = document.querySelector('.review');
const id = root.dataset.episode;
const $ = (x) => document.getElementById(x);
const video = $('video');
/** What shows the episode: the video element, or a MomentPlayer while there is no video. */
let player = video;
let data = null;
let fps = 20;
let byFrame = new Map(); // video frame -> telemetry row
let duration = 0;
let shownObservation = null;
// The agent's transcript cut at the robot's calls: call event_index -> the agent events before it.
const agent = { before: new Map(), after: [], shownFor: undefined, loaded: false, pinned: null };

/** Video time (s) of the state after control step c (middle of its frame). */
function timeOfStep(c) {
  const row = data.telemetry.find((r) => r.control_step === c);
  return row && row.video_frame != null ? (row.video_frame + 0.5) / fps : null;
}

function frameAt(t) {
  return Math.max(0, Math.floor(t * fps + 1e-6));
}

function stepAt(t) {
  const row = byFrame.get(frameAt(t));
  return row ? row.control_step : null;
}

/** The last call answered at or before time t. */
function callAt(t) {
  let found = null;
  for (const c of data.calls) {
    if (c.t != null && c.t <= t + 0.5 / fps) found = c;
  }
  return found;
}

function seek(t) {
  const max = duration || player.duration || 0;
  player.currentTime = Math.min(Math.max(0, t), Math.max(0, max - 1e-3));
  update();
}

/**
 * Plays the episode from moments rendered on demand: the same interface as the video element where the page uses
 * it (currentTime, duration, paused, play, pause, readyState and its events). One moment is fetched at a time; while
 * playing, the newest moment due is fetched next, so playback keeps the episode's pace and skips what the renderer
 * has no time for.
 */
class MomentPlayer extends EventTarget {
  constructor(img, note) {
    super();
    this.img = img; this.note = note;
    this.t = 0; this.paused = true; this.readyState = 4;
    this.wanted = null; this.loading = null; this.lastTick = 0;
    this.shownStep = null; this.failures = 0;
  }

  get duration() { return duration; }
  get currentTime() { return this.t; }
  set currentTime(t) { this.t = t; this.request(); this.dispatchEvent(new Event('seeked')); }

  play() {
    if (!this.paused) return;
    if (this.t >= duration - 1 / fps) this.t = 0;
    this.paused = false; this.lastTick = performance.now();
    this.dispatchEvent(new Event('play'));
    requestAnimationFrame(() => this.tick());
  }

  pause() {
    if (this.paused) return;
    this.paused = true;
    this.dispatchEvent(new Event('pause'));
  }

  tick() {
    if (this.paused) return;
    const now = performance.now();
    this.t = Math.min(duration, this.t + (now - this.lastTick) / 1000);
    this.lastTick = now;
    this.request();
    this.dispatchEvent(new Event('timeupdate'));
    if (this.t >= duration - 1e-3) this.pause(); else requestAnimationFrame(() => this.tick());
  }

  /** Fetches the moment of the current time, after the one being fetched if any. */
  request() {
    const step = stepAt(this.t) ?? 0;
    this.wanted = step;
    if (this.loading === null && step !== this.shownStep) this.load(step);
  }

  async load(step) {
    this.loading = step;
    this.img.setAttribute('aria-busy', 'true');
    try {
      const r = await fetch(`/api/episodes/${encodeURIComponent(id)}/moment?step=${step}`);
      if (!r.ok) {
        const body = await r.json().catch(() => ({}));
        throw new Error(body.error ?? `HTTP ${r.status}`);
      }
      showBlob(this.img, await r.blob());
      this.shownStep = step; this.failures = 0;
      this.img.dataset.step = String(step);
      this.img.alt = `head | wrist at control step ${step}`;
      this.note.classList.remove('error');
      this.note.textContent = this.baseNote;
    } catch (err) {
      this.failures += 1;
      this.note.classList.add('error');
      this.note.textContent = `control step ${step} could not be shown: ${err.message}`;
    } finally {
      this.loading = null;
      this.img.removeAttribute('aria-busy');
      if (this.wanted !== null && this.wanted !== this.shownStep && this.failures < 3) this.load(this.wanted);
    }
  }
}

/** Shows `p` (the video or a MomentPlayer) and follows its events. */
const bound = new WeakSet();
function bindPlayer(p) {
  player = p;
  if (bound.has(p)) return;
  bound.add(p);
  p.addEventListener('play', () => { $('play').textContent = 'pause'; });
  p.addEventListener('pause', () => { $('play').textContent = 'play'; update(); });
  p.addEventListener('seeked', update);
  p.addEventListener('timeupdate', update);
}

// ---- drawing

function xOf(t, w) { return duration > 0 ? (t / duration) * w : 0; }

function drawTimeline() {
  const c = $('timeline'); const g = c.getContext('2d');
  g.clearRect(0, 0, c.width, c.height);
  g.fillStyle = '#f3f4f6'; g.fillRect(0, 0, c.width, c.height);
  for (const call of data.calls) {
    if (call.t == null) continue;
    const x0 = call.t0 != null ? xOf(call.t0, c.width) : xOf(call.t, c.width);
    const x1 = xOf(call.t, c.width);
    g.fillStyle = call.ok ? 'rgba(37,99,235,0.25)' : 'rgba(220,38,38,0.35)';
    g.fillRect(x0, 8, Math.max(2, x1 - x0), 24);
    g.fillStyle = call.ok ? '#2563eb' : '#dc2626';
    g.fillRect(x1 - 1, 4, 2, 32);
  }
  // A tick where the agent did something between two calls (the video stands still meanwhile).
  g.fillStyle = '#7c3aed';
  for (const call of data.calls) {
    if ((agent.before.get(call.event_index) ?? []).length === 0) continue;
    if (call.t != null) g.fillRect(xOf(call.t, c.width) - 1, 60, 3, 9);
  }
  for (const e of data.stage_events) {
    if (e.t == null) continue;
    const x = xOf(e.t, c.width);
    g.fillStyle = e.kind === 'stage_completed' || e.kind === 'goal_satisfied' ? '#16a34a' : '#d97706';
    g.beginPath(); g.moveTo(x, 40); g.lineTo(x - 6, 56); g.lineTo(x + 6, 56); g.fill();
  }
  const x = xOf(player.currentTime, c.width);
  g.fillStyle = '#111'; g.fillRect(x - 1, 0, 2, c.height);
}

/** Seconds between time-axis ticks: a round step giving at most about 10 ticks over `span` seconds. */
function tickStep(span) {
  return [0.5, 1, 2, 5, 10, 15, 30, 60, 120, 300, 600, 1200, 1800, 3600].find((s) => span / s <= 10) ?? 7200;
}

/**
 * One telemetry plot against video time (= sim time): title with the unit, a legend naming each coloured line,
 * the value range at the right, and a time axis in seconds at the bottom.
 */
function drawPlot(canvasId, title, series, labels, colors) {
  const c = $(canvasId); const g = c.getContext('2d');
  g.clearRect(0, 0, c.width, c.height);
  const rows = data.telemetry.filter((r) => r.video_frame != null);
  const values = series.flatMap((f) => rows.map(f)).filter(Number.isFinite);
  g.font = '12px sans-serif'; g.textBaseline = 'alphabetic';
  g.fillStyle = '#374151'; g.fillText(title, 4, 12);
  // Legend: a swatch and a name per line, after the title.
  let lx = g.measureText(title).width + 16;
  labels.forEach((label, k) => {
    g.fillStyle = colors[k]; g.fillRect(lx, 5, 14, 3);
    g.fillStyle = '#374151'; g.fillText(label, lx + 18, 12);
    lx += 18 + g.measureText(label).width + 12;
  });
  const top = 18; const axis = 16; const h = c.height - top - axis;
  // Time axis: ticks every round number of seconds of video (= sim) time.
  g.strokeStyle = '#9ca3af'; g.lineWidth = 1; g.beginPath(); g.moveTo(0, top + h + 0.5); g.lineTo(c.width, top + h + 0.5); g.stroke();
  if (duration > 0) {
    const step = tickStep(duration);
    g.fillStyle = '#6b7280'; g.font = '10px sans-serif';
    for (let t = 0; t <= duration + 1e-9; t += step) {
      const x = xOf(t, c.width);
      g.fillRect(x, top + h, 1, 4);
      const label = `${Number.isInteger(t) ? t : t.toFixed(1)} s`;
      const w = g.measureText(label).width;
      if (x + w / 2 < c.width - 46) g.fillText(label, Math.max(0, x - w / 2), c.height - 2); // clear of the unit
    }
    g.fillText('time (s)', c.width - 38, c.height - 2);
    g.font = '12px sans-serif';
  }
  if (rows.length < 2 || values.length === 0) return;
  let lo = Math.min(...values); let hi = Math.max(...values);
  if (hi - lo < 1e-9) { lo -= 1; hi += 1; }
  const yOf = (v) => top + h - ((v - lo) / (hi - lo)) * h;
  series.forEach((f, k) => {
    g.strokeStyle = colors[k]; g.lineWidth = 1.5; g.beginPath();
    rows.forEach((r, i) => {
      const x = xOf((r.video_frame + 0.5) / fps, c.width); const y = yOf(f(r));
      if (i === 0) g.moveTo(x, y); else g.lineTo(x, y);
    });
    g.stroke();
  });
  g.fillStyle = '#6b7280'; g.font = '11px sans-serif';
  g.fillText(`${hi.toPrecision(3)}`, c.width - 60, top + 10); g.fillText(`${lo.toPrecision(3)}`, c.width - 60, top + h - 3);
  const x = xOf(player.currentTime, c.width);
  g.fillStyle = '#111'; g.fillRect(x - 1, top, 2, h);
}

function drawAll() {
  if (!data) return;
  drawTimeline();
  drawPlot('plot-eef', 'end-effector position in robot base (m)', [(r) => r.eef_pos_in_base_m[0], (r) => r.eef_pos_in_base_m[1], (r) => r.eef_pos_in_base_m[2]],
    ['x', 'y', 'z'], ['#dc2626', '#16a34a', '#2563eb']);
  drawPlot('plot-gripper', 'gripper opening (m)', [(r) => r.gripper_qpos_m[0] - r.gripper_qpos_m[1]], ['finger joint 1 − finger joint 2'], ['#7c3aed']);
  drawPlot('plot-force', 'wrist force (N)', [(r) => r.wrist_force_n[0], (r) => r.wrist_force_n[1], (r) => r.wrist_force_n[2], (r) => Math.hypot(...r.wrist_force_n)],
    ['x', 'y', 'z', '|f|'], ['#dc2626', '#16a34a', '#2563eb', '#111']);
}

// ---- panels

async function showObservation(obsId) {
  if (obsId === shownObservation) return;
  shownObservation = obsId;
  const box = $('observation');
  if (!obsId) { box.textContent = '–'; return; }
  const base = `/episodes/${encodeURIComponent(id)}/observations/${obsId}`;
  box.replaceChildren(el('div', { class: 'muted' }, obsId));
  const imgs = el('div', { class: 'obs-images' });
  const slots = {};
  for (const cam of ['head', 'wrist']) {
    imgs.append(el('img', { src: `${base}/${cam}/rgb.png`, alt: `${cam} rgb`, title: `${cam} rgb`, width: 128, height: 128 }));
    slots[cam] = el('span');
    imgs.append(slots[cam]);
  }
  box.append(imgs);
  try {
    const r = await fetch(`${base}/observation.json`);
    if (!r.ok) throw new Error(`HTTP ${r.status}`);
    const doc = await r.json();
    if (shownObservation !== obsId) return;
    // Depth only where the observation names a preview file (level 3): levels 1-2 publish none, so none is asked for.
    for (const cam of ['head', 'wrist']) {
      const file = doc.cameras?.[cam]?.depth?.preview_file;
      if (typeof file === 'string' && /^[a-z]+\/[a-z_]+\.png$/.test(file)) {
        slots[cam].replaceWith(el('img', { src: `${base}/${file}`, alt: `${cam} depth`, title: `${cam} depth preview`, width: 128, height: 128 }));
      }
    }
    const robot = doc.robot_state ?? doc.robot ?? doc.proprioception ?? doc;
    box.append(el('pre', { class: 'state' }, JSON.stringify(robot, null, 1).slice(0, 4000)));
  } catch (err) {
    box.append(el('div', { class: 'error' }, `observation.json: ${err}`));
  }
}

function update() {
  if (!data) return;
  const t = player.currentTime;
  $('time').textContent = fmtS(t);
  const step = stepAt(t);
  $('cstep').textContent = step ?? 'settle';
  const link = new URL(location.href); link.searchParams.set('t', t.toFixed(2));
  $('deeplink').href = link.pathname + link.search;
  // A call picked from the transcript stays selected while the video stays at its moment (calls without control
  // steps share their moment with the call before them).
  const pinned = agent.pinned && Math.abs(t - agent.pinned.at) < 0.5 / fps ? agent.pinned.call : null;
  if (!pinned) agent.pinned = null;
  const call = pinned ?? callAt(t);
  $('call-detail').textContent = call
    ? `#${call.event_index} ${callSummary(call.tool, call.actions)} → ${call.ok ? 'ok' : `${call.error_type}: ${call.error}`} (steps ${call.control_step_begin}–${call.control_step_end})`
    : '–';
  showObservation(call?.observation_id ?? null);
  showAgent(call);
  for (const li of $('events').children) li.classList.toggle('current', li.dataset.t && Math.abs(Number(li.dataset.t) - (call?.t ?? -1)) < 1e-9);
  drawAll();
}

/** What the agent did before `call`: its transcript between the previous call and this one, and the images it
 * viewed there (published observation files open from the episode's private copy; others are named only). */
function showAgent(call) {
  const key = call?.event_index ?? null;
  if (!agent.loaded || agent.shownFor === key) return;
  agent.shownFor = key;
  const events = call ? agent.before.get(call.event_index) ?? [] : [];
  $('agent-count').textContent = call ? `(${events.length} events before call #${call.event_index})` : '';
  $('agent-before').replaceChildren(...(events.length ? events.map(agentEventItem) : [el('li', { class: 'muted' }, call ? 'nothing between the previous call and this one' : '–')]));
  const views = events.filter((e) => e.kind === 'image_view');
  const box = $('agent-images');
  box.classList.toggle('muted', views.length === 0);
  box.replaceChildren(...(views.length ? views.map((e) => {
    const fig = el('figure');
    if (e.observation_url) fig.append(el('img', { src: e.observation_url, alt: e.observation_file, width: 128, height: 128 }));
    fig.append(el('figcaption', {}, e.observation_url ? `${e.observation_id}/${e.observation_file}` : `${e.path} (not a published observation file: not shown)`));
    return fig;
  }) : [document.createTextNode('–')]));
}

/** Loads the agent's timeline page by page and cuts it at the robot's calls. */
async function loadAgent() {
  const api = `/api/episodes/${encodeURIComponent(id)}/agent`;
  let page = await (await fetch(api)).json();
  const items = [...(page.timeline ?? [])];
  const available = page.available;
  while (page.timeline_next) {
    const q = new URLSearchParams(Object.entries(page.timeline_next).filter(([, v]) => v !== null && v !== undefined));
    page = await (await fetch(`${api}?${q}`)).json();
    items.push(...(page.timeline ?? []));
  }
  const byIndex = new Map(data.calls.map((c) => [c.event_index, c]));
  const log = [];
  let pending = [];
  for (const it of items) {
    if (it.kind === 'robot_call') {
      agent.before.set(it.event_index, pending);
      for (const e of pending) log.push([e, byIndex.get(it.event_index)]);
      pending = [];
    } else pending.push(it);
  }
  agent.after = pending;
  for (const e of pending) log.push([e, null]);
  agent.loaded = true;
  $('agent-log').replaceChildren(...(log.length ? log.map(([e, call]) => {
    const li = agentEventItem(e);
    if (call) {
      li.title = `${e.t} · before call #${call.event_index} ${call.tool}`;
      li.addEventListener('click', () => {
        player.pause();
        seek(call.t ?? 0);
        agent.pinned = { call, at: player.currentTime };
        update();
      });
    } else li.title = `${e.t} · after the last call`;
    return li;
  }) : [el('li', { class: 'muted' }, available ? 'the transcript is empty' : 'no transcript for this episode (not run by libero-agent run)')]));
  document.body.dataset.agentEvents = String(log.length);
  document.body.dataset.agentText = log.map(([e]) => agentEventText(e)).join('\n').slice(0, 20000);
}

/** Calls of at most this many actions are teleop-sized (the teleop page sends 2 at a time). */
const SHORT_CALL_ACTIONS = 5;

/**
 * The calls as timeline rows: a run of three or more accepted teleop-sized `osc_sequence` calls with no stage event
 * in it is one row ("146 short calls · 292 actions, steps 40–332"), so a teleop episode's timeline is not
 * flooded; every other call is a row of its own.
 */
function callRows() {
  const rows = [];
  let run = [];
  const stageSteps = data.stage_events.map((e) => e.control_step).filter((c) => c != null);
  const flush = () => {
    if (run.length >= 3) {
      const actions = run.reduce((n, c) => n + (c.actions ?? 0), 0);
      const [first, last] = [run[0], run[run.length - 1]];
      rows.push({ t: first.t0 ?? first.t, cls: 'ok grouped', text: `${run.length} short osc_sequence calls · ${actions} actions, steps ${first.control_step_begin}–${last.control_step_end}`,
        title: run.map((c) => `#${c.event_index} ${callSummary(c.tool, c.actions)}`).join('\n') });
    } else {
      for (const c of run) rows.push(callRow(c));
    }
    run = [];
  };
  for (const c of data.calls) {
    const short = c.ok && c.tool === 'osc_sequence' && (c.actions ?? 0) > 0 && c.actions <= SHORT_CALL_ACTIONS;
    // A stage event during the run's last call ends the run there, so the event stands between two rows.
    const last = run[run.length - 1];
    const stageInside = last != null && stageSteps.some((s) => s > last.control_step_begin && s <= last.control_step_end);
    if (!short || stageInside) flush();
    if (short) run.push(c); else rows.push(callRow(c));
  }
  flush();
  return rows;
}

function callRow(c) {
  return { t: c.t, cls: c.ok ? 'ok' : 'error', text: `${callSummary(c.tool, c.actions)} ${c.ok ? 'ok' : `${c.error_type}: ${c.error}`}` };
}

function buildEvents() {
  const items = [
    ...callRows(),
    ...data.stage_events.map((e) => ({ t: e.t, cls: e.kind, text: stageText(e) })),
  ].sort((a, b) => (a.t ?? -1) - (b.t ?? -1));
  $('events').replaceChildren(...items.map((it) => {
    const li = el('li', { class: it.cls, 'data-t': it.t ?? '', title: it.title ?? '' }, `${it.t != null ? fmtS(it.t) : '–'} s · ${it.text}`);
    if (it.t != null) li.addEventListener('click', () => { player.pause(); seek(it.t); });
    return li;
  }));
}

/** An element with child nodes. */
function node(tag, attrs, ...children) {
  const e = el(tag, attrs);
  e.append(...children);
  return e;
}

/**
 * A record's `failure_reason` in words (the record keeps its machine-readable value). `terminal_state_invalid` is
 * the ordinary "the goal did not hold when the episode ended", not an error of the episode.
 */
const FAILURE_TEXT = {
  terminal_state_invalid: 'goal not met at the end',
  incomplete_stage: 'stage not completed',
  order_violation: 'done out of order',
  extra_pour: 'poured more than asked',
  forbidden_contact: 'forbidden contact',
  premature_lift_detected: 'lifted too early',
};
function failureText(reason) {
  return FAILURE_TEXT[reason] ?? String(reason).replaceAll('_', ' ');
}

/** Per-stage diagnostics of the record (reached / succeeded / regressions / sustained-contact ratio). */
function buildStages() {
  const stages = data.result?.private_evaluation?.stage_diagnostics ?? [];
  const table = $('stages');
  if (stages.length === 0) {
    table.replaceChildren(node('tbody', {}, node('tr', {}, el('td', { class: 'muted' }, 'no staged evaluation'))));
    return;
  }
  const head = node('tr', {}, ...['', 'stage', 'reached', 'done at', 'regressed', 'sustained contact'].map((h) => el('th', {}, h)));
  const rows = stages.map((s) => {
    const state = s.succeeded ? 'succeeded' : s.reached ? 'failed' : 'unreached';
    const t = s.completed_control_step != null ? timeOfStep(s.completed_control_step) : null;
    const scr = s.sustained_contact_ratio_percent != null
      ? `${s.sustained_contact_ratio_percent.toFixed(0)}% of ${s.contact_exec_steps} steps` : '';
    const regressed = s.regressions > 0
      ? `${s.regressions}×${s.regressed_during_later_stage ? ' (undone by a later stage)' : ''}` : '';
    const name = `${stageLabel(s.stage_name)}${s.required ? '' : ' (optional)'}${s.failure_reason ? ` — ${failureText(s.failure_reason)}` : ''}`;
    const tr = node('tr', { class: state, 'data-t': t ?? undefined },
      el('td', { class: 'mark' }, s.succeeded ? '✔' : s.reached ? '✘' : '·'),
      el('td', { title: s.stage_name }, name),
      el('td', {}, s.reached ? 'yes' : 'no'),
      el('td', {}, s.completed_control_step != null ? `step ${s.completed_control_step}` : '–'),
      el('td', {}, regressed),
      el('td', {}, scr));
    if (t != null) tr.addEventListener('click', () => { player.pause(); seek(t); });
    return tr;
  });
  table.replaceChildren(node('thead', {}, head), node('tbody', {}, ...rows));
}

// ---- input

function stepBy(k) {
  player.pause();
  seek((frameAt(player.currentTime) + k + 0.5) / fps);
}

function scrub(ev) {
  const c = $('timeline'); const r = c.getBoundingClientRect();
  seek(((ev.clientX - r.left) / r.width) * duration);
}

$('timeline').addEventListener('pointerdown', (ev) => {
  player.pause(); scrub(ev);
  const move = (e) => scrub(e);
  window.addEventListener('pointermove', move);
  window.addEventListener('pointerup', () => window.removeEventListener('pointermove', move), { once: true });
});
$('play').addEventListener('click', () => (player.paused ? player.play() : player.pause()));
$('prev').addEventListener('click', () => stepBy(-1));
$('next').addEventListener('click', () => stepBy(1));
document.addEventListener('keydown', (e) => {
  if (e.target instanceof HTMLInputElement) return;
  if (e.key === 'ArrowLeft') { e.preventDefault(); stepBy(-1); }
  if (e.key === 'ArrowRight') { e.preventDefault(); stepBy(1); }
  if (e.key === ' ') { e.preventDefault(); if (player.paused) player.play(); else player.pause(); }
});
bindPlayer(video);
function animate() { if (!player.paused && player === video) update(); requestAnimationFrame(animate); }
requestAnimationFrame(animate);

// ---- load

// The private video is rendered from the episode's state record after it ends. Until it is there (or for an episode
// without one), moments are rendered from the recorded state; a video that becomes ready replaces them at the same
// moment.
function videoStatusText(st) {
  if (!st) return 'This episode records no video: each moment is rendered from the recorded state.';
  if (st.state === 'failed') return `The video could not be rendered (${st.error}): each moment is rendered from the recorded state.`;
  const percent = st.state === 'queued' ? '0 % (queued)' : `${st.percent ?? 0} %`;
  return `video rendering, ${percent}: meanwhile each moment is rendered from the recorded state.`;
}

function useMoments(api, status) {
  const note = el('p', { id: 'video-status', class: 'muted' }, videoStatusText(status));
  const img = el('img', { id: 'moment', width: 512, height: 256, alt: 'head | wrist' });
  const box = el('div', { class: 'moment' });
  box.append(img, note);
  video.replaceWith(box);
  const moments = new MomentPlayer(img, note);
  moments.baseNote = note.textContent;
  bindPlayer(moments);
  document.body.dataset.player = 'moments';
  if (!status || status.state === 'failed') return;
  const poll = async () => {
    const v = await (await fetch(`${api}?part=video`)).json().catch(() => ({}));
    if (v.video) {
      const at = moments.currentTime;
      moments.pause();
      box.replaceWith(video);
      bindPlayer(video);
      document.body.dataset.player = 'video';
      video.addEventListener('loadedmetadata', () => seek(at), { once: true });
      video.load();
      return;
    }
    moments.baseNote = videoStatusText(v.video_status);
    if (!note.classList.contains('error')) note.textContent = moments.baseNote;
    if (v.video_status && v.video_status.state !== 'failed') setTimeout(poll, 1000);
  };
  setTimeout(poll, 1000);
}

async function load() {
  const api = `/api/episodes/${encodeURIComponent(id)}/review`;
  data = await (await fetch(api)).json();
  // Long episodes come in pages: follow each part's cursor to its end.
  for (const part of ['calls', 'telemetry']) {
    let next = data[`${part}_next`];
    while (next) {
      const q = new URLSearchParams({ part, from: next.from, control_step: next.control_step ?? 0 });
      const page = await (await fetch(`${api}?${q}`)).json();
      data[part].push(...page[part]);
      next = page[`${part}_next`];
    }
  }
  fps = data.video_fps || 20;
  // Without a video the telemetry names no video frames: one frame per control step, as the video would have.
  if (!data.telemetry.some((r) => r.video_frame != null)) for (const r of data.telemetry) r.video_frame = r.control_step;
  byFrame = new Map(data.telemetry.filter((r) => r.video_frame != null).map((r) => [r.video_frame, r]));
  for (const c of data.calls) {
    c.t = timeOfStep(c.control_step_end);
    c.t0 = timeOfStep(c.control_step_begin);
  }
  for (const e of data.stage_events) e.t = timeOfStep(e.control_step);
  const last = data.telemetry.reduce((m, r) => Math.max(m, r.video_frame ?? 0), 0);
  duration = (last + 1) / fps;
  $('result').textContent = JSON.stringify(data.result, null, 2);
  if (!data.video) useMoments(api, data.video_status);
  buildEvents();
  buildStages();
  await loadAgent().catch((err) => { $('agent-log').replaceChildren(el('li', { class: 'error' }, `cannot load the agent's transcript: ${err}`)); });
  const t = Number(new URL(location.href).searchParams.get('t'));
  const start = () => { if (Number.isFinite(t) && t > 0) seek(t); else update(); };
  if (player.readyState >= 1) start(); else player.addEventListener('loadedmetadata', start, { once: true });
  document.body.dataset.ready = 'true';
}

load().catch((err) => { $('result').textContent = `cannot load the review: ${err}`; });
