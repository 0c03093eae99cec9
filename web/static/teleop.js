// Teleop page: keyboard (robosuite 1.4 key map) and Gamepad API → normalized OSC_POSE actions, one per 50 ms
// tick in real time, sent in small batches over /ws/teleop/<id> (each batch is one osc_sequence call in the
// episode's own thread); frames, stage progress and calls come from the ordinary live stream /ws/episodes/<id>.
// The episode is made on the first input (opening the page makes none); a branch page starts with its parent's
// last gripper command, so what the robot holds stays held.
import { wsUrl, el, callSummary, parseFrame, showBlob, postJson, showEvaluatorEvent, verdictText, finishEpisode, abortEpisode } from './common.js';

const root = document.querySelector('.teleop');
const task = root.dataset.task;
const seed = Number(root.dataset.seed);
const $ = (x) => document.getElementById(x);
const TICK_MS = 50;
/** Batches allowed in flight; beyond that the page stops generating (sim time slows, the rate label shows it). */
const MAX_IN_FLIGHT = 2;
/** A branch page (the review's "Continue from here") starts every episode from the parent's state at that step. */
const branch = root.dataset.branchParent ? { parent: root.dataset.branchParent, step: Number(root.dataset.branchStep) } : undefined;
/** The gripper command every episode of the page starts with: open, or a branch's parent's last command. */
const START_GRIPPER = Number(root.dataset.gripper ?? -1);

// robosuite 1.4 keyboard: w/s ∓x, a/d ∓y, r/f ±z, z/x t/g c/v ± rotation about x, y, z (component, sign).
const KEYS = { w: [0, -1], s: [0, 1], a: [1, -1], d: [1, 1], r: [2, 1], f: [2, -1],
  z: [3, 1], x: [3, -1], t: [4, 1], g: [4, -1], c: [5, 1], v: [5, -1] };

const held = new Set();
let s = null; // the current episode's session (null: none yet, the next input makes one)
let starting = false;
let gripper = START_GRIPPER;

function newSession(id) {
  return { id, control: null, live: null, queue: [], inFlight: 0, seq: 0, sent: 0, acked: 0, generated: 0,
    nextTick: performance.now(), acks: [], latency: null, frames: 0, paused: false, ended: false, saving: false,
    byOperator: false, aborted: false, judged: false, flushWaiters: [] };
}

function setState(text) { $('state').textContent = text; }

const gripperLabel = (g) => (g > 0 ? 'closed' : g < 0 ? 'open' : 'unchanged (0)');
function showGripper() { $('gripper').textContent = gripperLabel(gripper); }

/** The message line under the controls: `kind` is its class (verified, unverified, error, pending, …). */
function showResult(kind, ...parts) {
  const out = $('save-result');
  out.className = kind;
  delete out.dataset.bundle;
  delete out.dataset.verified;
  out.replaceChildren(...parts);
}

/** Reset: no episode, nothing left of the last one's messages, counters or gripper. */
function clearPage() {
  const out = $('save-result');
  out.replaceChildren();
  out.className = 'hidden';
  delete out.dataset.bundle;
  delete out.dataset.verified;
  $('episode').textContent = 'no episode yet';
  for (const x of ['frame-count', 'sent', 'acked']) $(x).textContent = '0';
  for (const x of ['rate', 'latency', 'progress', 'frame-step', 'exec']) $(x).textContent = '–';
  $('stages').replaceChildren(); $('calls').replaceChildren();
  gripper = START_GRIPPER;
  showGripper();
  $('hint').classList.remove('hidden');
  $('preview')?.classList.remove('hidden');
  $('frame').classList.add('hidden');
  setState('ready');
}

/** One action from the held keys and the gamepad, scaled by the speed slider. */
function currentAction() {
  const speed = Number($('speed').value);
  const a = [0, 0, 0, 0, 0, 0, 0];
  for (const k of held) {
    const m = KEYS[k];
    if (m) a[m[0]] += m[1];
  }
  const pad = gamepadAxes();
  for (let i = 0; i < 6; i++) a[i] = Math.max(-1, Math.min(1, (a[i] + pad[i]) * speed));
  a[6] = gripper;
  return a;
}

const DEADZONE = 0.15;
let padButtonsBefore = [];
/** Gamepad contribution [dx..rz] in [-1, 1]; the A button toggles the gripper on its press. */
function gamepadAxes() {
  const out = [0, 0, 0, 0, 0, 0];
  const pads = navigator.getGamepads ? [...navigator.getGamepads()].filter(Boolean) : [];
  if (!pads.length) return out;
  const p = pads[0];
  $('gamepad').textContent = p.id;
  const ax = (i) => (Math.abs(p.axes[i] ?? 0) > DEADZONE ? p.axes[i] : 0);
  const btn = (i) => (p.buttons[i] ? p.buttons[i].value : 0);
  out[0] = ax(1); out[1] = ax(0); out[2] = -ax(3); out[5] = -ax(2);
  out[3] = btn(5) - btn(4); out[4] = btn(7) - btn(6);
  const pressed = p.buttons.map((b) => b.pressed);
  if (pressed[0] && !padButtonsBefore[0]) toggleGripper();
  padButtonsBefore = pressed;
  return out;
}

function toggleGripper() {
  if (s?.ended) return;
  gripper = gripper > 0 ? -1 : 1;
  showGripper();
  markLatency();
  begin();
}

/** The first input makes the page's episode (none exists before; after one ended, Reset makes way for the next). */
function begin() {
  if (!s && !starting) start();
}

/** Starts a latency measurement: the next generated action carries the input; its effect shows in the frame
 * whose control step is that action's index + 1. */
function markLatency() {
  if (s && !s.latency) s.latency = { t0: performance.now(), target: s.generated + 1 };
}

function tick() {
  if (!s) {
    // No episode yet: only watch the gamepad for the input that makes one.
    if (gamepadAxes().some((x) => x !== 0)) begin();
    return;
  }
  if (s.paused || s.ended || !s.control || s.control.readyState !== WebSocket.OPEN) {
    s.nextTick = performance.now();
    return;
  }
  const batch = Number($('batch').value);
  const now = performance.now();
  // Real time: one action per elapsed 50 ms, unless the sim is behind (then time stretches, never a backlog).
  while (s.nextTick <= now && s.inFlight < MAX_IN_FLIGHT) {
    s.queue.push(currentAction());
    s.generated++;
    s.nextTick += TICK_MS;
    if (s.queue.length >= batch) sendBatch();
  }
  if (s.nextTick < now - 10 * TICK_MS) s.nextTick = now;
}

function sendBatch() {
  if (!s.queue.length) return;
  const actions = s.queue.splice(0, s.queue.length);
  s.control.send(JSON.stringify({ seq: ++s.seq, actions }));
  s.inFlight++;
  s.sent += actions.length;
  $('sent').textContent = s.sent;
}

function onAck(a) {
  s.inFlight = Math.max(0, s.inFlight - 1);
  if (a.ok) {
    s.acked += a.actions;
    s.acks.push({ t: performance.now(), n: a.actions });
  }
  $('acked').textContent = s.acked;
  $('exec').textContent = a.exec_ms !== undefined ? `${a.exec_ms.toFixed(0)} ms / ${a.actions} actions` : '–';
  const horizon = performance.now() - 2000;
  s.acks = s.acks.filter((x) => x.t >= horizon);
  if (s.acks.length >= 2) {
    const n = s.acks.slice(1).reduce((m, x) => m + x.n, 0);
    const span = (s.acks[s.acks.length - 1].t - s.acks[0].t) / 1000;
    if (span > 0) $('rate').textContent = (n / span).toFixed(1);
  }
  if (!a.ok) $('calls').prepend(el('li', { class: 'error' }, `osc_sequence: ${a.error_type ?? ''} ${a.error ?? ''}`));
  if (s.inFlight === 0 && !s.queue.length) { s.flushWaiters.forEach((f) => f()); s.flushWaiters = []; }
}

/** The control socket's answers: action acks, and the save's progress and result. */
function onControl(m) {
  switch (m.type) {
    case 'ack': onAck(m); break;
    case 'save_progress': showSaveProgress(m); break;
    case 'saved': showSaved(m); break;
    case 'save_failed': showSaved(m); break;
    default: if (m.error) $('calls').prepend(el('li', { class: 'error' }, m.error)); break;
  }
}

function onFrame(buf) {
  const { header, blob } = parseFrame(buf);
  $('preview')?.classList.add('hidden');
  $('frame').classList.remove('hidden');
  showBlob($('frame'), blob);
  $('frame-step').textContent = header.control_step ?? 'settle';
  $('frame-count').textContent = ++s.frames;
  if (s.latency && header.control_step != null && header.control_step >= s.latency.target) {
    const ms = performance.now() - s.latency.t0;
    $('latency').textContent = `${ms.toFixed(0)} ms`;
    s.latency = null;
  }
}

function onEvent(e) {
  if (showEvaluatorEvent(e, $('stages'), $('progress'))) return;
  switch (e.type) {
    case 'call_answered':
      if (e.tool !== 'osc_sequence' || !e.ok) $('calls').prepend(el('li', { class: e.ok ? 'ok' : 'error' }, `${callSummary(e.tool, e.actions)}: ${e.ok ? 'ok' : e.error}`));
      break;
    case 'finished':
      s.ended = true;
      // While a demonstration is saved the verdict is not the page's result yet: the replay still verifies it.
      if (!s.saving && !s.byOperator) {
        setState(e.outcome ?? e.state);
        // Ended by nobody on this page (abandoned, the wall-time budget, another page's Abort): say why.
        showResult('error', `the episode ended: ${e.outcome ?? e.state}${e.reason ? ` — ${e.reason}` : ''}`);
      }
      break;
    default:
      break;
  }
}

/** Prepares and starts a new operator episode of this task and seed, then opens its two sockets. */
async function start() {
  starting = true;
  setState('starting');
  $('hint').classList.add('hidden');
  const r = await postJson('/api/teleop', branch ? { branch } : { task, seed });
  starting = false;
  if (!r.ok) { setState('error'); showResult('error', `no episode: ${r.error}`); return; }
  s = newSession(r.episode_id);
  $('episode').textContent = r.episode_id;
  const session = s;
  const live = new WebSocket(wsUrl(`/ws/episodes/${encodeURIComponent(r.episode_id)}`));
  live.binaryType = 'arraybuffer';
  live.onmessage = (m) => { if (s === session) { if (typeof m.data === 'string') onEvent(JSON.parse(m.data)); else onFrame(m.data); } };
  const control = new WebSocket(wsUrl(`/ws/teleop/${encodeURIComponent(r.episode_id)}`));
  control.onmessage = (m) => { if (s === session) onControl(JSON.parse(m.data)); };
  control.onopen = () => { if (s === session) { s.nextTick = performance.now(); setState('driving'); } };
  control.onclose = () => { if (s === session && !s.ended) setState('disconnected'); };
  s.live = live; s.control = control;
  root.focus();
}

function close(session) {
  session.ended = true;
  session.control?.close();
  session.live?.close();
}

/** Waits until every queued action has been executed. */
function flush() {
  if (s.ended || !s.control || s.control.readyState !== WebSocket.OPEN) return Promise.resolve();
  sendBatch();
  if (s.inFlight === 0) return Promise.resolve();
  return new Promise((res) => s.flushWaiters.push(res));
}

/** The replay that records and verifies the demonstration, as it goes (10–40 s). */
function showSaveProgress(m) {
  setState('verifying');
  const seconds = `${Math.round(m.elapsed_s ?? 0)} s`;
  if (m.phase === 'replaying') {
    showResult('pending', 'recording the demonstration and verifying it by replay: frame ',
      el('b', { id: 'save-frames' }, `${m.done} / ${m.total}`), ` · ${seconds} `,
      el('progress', { id: 'save-progress', max: String(m.total), value: String(m.done) }));
  } else {
    showResult('pending', `finishing the episode and starting the replay … ${seconds}`);
  }
}

function showSaved(r) {
  const session = s;
  if (session) { session.saving = false; close(session); }
  if (!r.ok) {
    showResult('error', `not saved: ${r.error}`);
    setState('save failed');
    return;
  }
  showResult(r.verified ? 'verified' : 'unverified', `saved ${r.bundle} (${r.transition_count} actions, ${r.frame_count} frames${r.branch ? `, after the ${r.branch.replayed_actions} replayed actions of ${r.branch.parent_episode_id}` : ''}): `,
    el('b', { id: 'verdict' }, r.verified ? 'verified by replay' : 'not verified'),
    r.reason ? ` — ${r.reason}` : '', ` (${Math.round(r.elapsed_s ?? 0)} s) · `, el('a', { href: '/demos' }, 'demos'));
  const out = $('save-result');
  out.dataset.bundle = r.bundle;
  out.dataset.verified = String(r.verified);
  setState('saved');
}

$('pause').onclick = () => {
  if (!s || s.ended) return;
  s.paused = !s.paused;
  $('pause').textContent = s.paused ? 'Resume' : 'Pause';
  setState(s.paused ? 'paused' : 'driving');
  s.nextTick = performance.now();
};
$('reset').onclick = async () => {
  const old = s;
  s = null;
  $('pause').textContent = 'Pause';
  clearPage();
  if (old) {
    close(old);
    if (!old.byOperator && !old.saving) await abortEpisode(old.id, 'reset by the operator (teleop page)');
  }
};
$('abort').onclick = async () => {
  if (!s || s.ended || s.saving) return;
  const session = s;
  session.byOperator = true;
  session.aborted = true;
  close(session);
  const r = await abortEpisode(session.id, 'aborted by the operator (teleop page)');
  setState(r.ok === false ? 'abort failed' : 'aborted');
  showResult(r.ok === false ? 'error' : 'unverified', r.ok === false ? `not aborted: ${r.error}` : `aborted ${session.id}: nothing was saved · Reset starts a new episode`);
};
$('finish').onclick = async () => {
  if (!s || s.ended || s.saving) return;
  const session = s;
  session.paused = true;
  setState('judging');
  await flush();
  session.byOperator = true;
  const v = await finishEpisode(session.id);
  session.ended = true;
  session.judged = true;
  setState(v.outcome ?? (v.ok ? 'finished' : 'error'));
  showResult(v.success ? 'verified' : 'unverified', 'judged: ', el('b', { id: 'judged' }, verdictText(v)),
    ' · Save demonstration records it, Reset starts a new episode');
};
$('save').onclick = async () => {
  // An open episode, or one judged here (it is recorded as it ended); never an aborted one.
  if (!s || s.saving || s.aborted || (s.ended && !s.judged)) return;
  const session = s;
  session.paused = true;
  session.saving = true;
  setState('saving');
  showResult('pending', 'finishing the episode …');
  await flush();
  if (session.control?.readyState === WebSocket.OPEN) {
    session.control.send(JSON.stringify({ type: 'save' }));
    return;
  }
  // No control socket any more: save without progress.
  const r = await postJson(`/api/teleop/${encodeURIComponent(session.id)}/save`);
  showSaved(r);
};

document.addEventListener('keydown', (e) => {
  if (e.target instanceof HTMLInputElement || e.target instanceof HTMLSelectElement) return;
  const k = e.key.toLowerCase();
  if (k === ' ') {
    e.preventDefault();
    if (!e.repeat) toggleGripper();
    return;
  }
  if (KEYS[k]) {
    e.preventDefault();
    if (!held.has(k)) { held.add(k); markLatency(); begin(); }
  }
});
document.addEventListener('keyup', (e) => held.delete(e.key.toLowerCase()));
window.addEventListener('blur', () => held.clear());
$('speed').oninput = () => { $('speed-value').textContent = Number($('speed').value).toFixed(2); };
setInterval(tick, 10);
clearPage();
