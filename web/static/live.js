// Live episode page: head | wrist frames, calls, private evaluator events, the agent's transcript and budgets as
// they happen.
// Frames arrive as binary messages (4-byte LE header length, JSON header, JPEG); everything else as JSON.
import { wsUrl, el, fmtS, callSummary, parseFrame, showBlob, showEvaluatorEvent, agentEventItem, verdictText, finishEpisode, abortEpisode } from './common.js';

const root = document.querySelector('.live');
const id = root.dataset.episode;
const $ = (x) => document.getElementById(x);
const img = $('frame');
const budget = { maxSteps: Number(root.dataset.maxSteps), maxWall: Number(root.dataset.maxWall), wall: null, at: null, running: true };
let frames = 0;
let pendingCall = null;

function showFrame(buf) {
  const { header, blob } = parseFrame(buf);
  showBlob(img, blob);
  $('frame-step').textContent = header.control_step ?? 'settle';
  $('frame-time').textContent = fmtS(header.sim_time_s);
  $('frame-index').textContent = header.video_frame ?? '–';
  $('frame-count').textContent = ++frames;
}

function onEvent(e) {
  if (showEvaluatorEvent(e, $('stages'), $('progress'))) return;
  switch (e.type) {
    case 'hello':
      budget.maxSteps = e.max_agent_steps; budget.maxWall = e.max_wall_time_s;
      $('max-steps').textContent = e.max_agent_steps;
      $('state').textContent = 'live';
      break;
    case 'reset':
      $('calls').replaceChildren(); $('stages').replaceChildren();
      break;
    case 'call_received':
      pendingCall = el('li', { class: 'pending' }, `→ ${callSummary(e.tool, e.actions)} …`);
      $('calls').prepend(pendingCall);
      break;
    case 'call_answered': {
      const text = `${callSummary(e.tool, e.actions)}: ${e.ok ? `ok ${e.observation_id ?? ''}` : `${e.error_type}: ${e.error}`}`;
      const li = pendingCall ?? el('li');
      li.className = e.ok ? 'ok' : 'error';
      li.textContent = text;
      if (!pendingCall) $('calls').prepend(li);
      pendingCall = null;
      $('submissions').textContent = e.accepted_agent_steps;
      budget.wall = e.wall_time_s; budget.at = e.at_unix_s;
      break;
    }
    case 'agent': {
      // The runner appends the agent's events as its CLI prints them; newest first, the last 500 kept.
      const list = $('agent');
      if (list.firstElementChild?.classList.contains('muted')) list.replaceChildren();
      for (const ev of e.events) list.prepend(agentEventItem(ev));
      while (list.children.length > 500) list.lastElementChild.remove();
      break;
    }
    case 'step':
      $('step').textContent = `${e.control_step} (${fmtS(e.sim_time_s)} s)`;
      break;
    case 'finished':
      budget.running = false;
      $('state').textContent = e.state;
      $('outcome').textContent = e.outcome ?? e.state;
      $('reason').textContent = e.reason ?? '';
      $('finished').classList.remove('hidden');
      for (const b of ['finish', 'abort']) $(b).disabled = true;
      break;
    default:
      break;
  }
}

function tickWall() {
  if (budget.wall == null) return;
  const elapsed = budget.running ? budget.wall + (Date.now() / 1000 - budget.at) : budget.wall;
  $('wall-left').textContent = `${fmtS(Math.max(0, budget.maxWall - elapsed), 0)} s`;
}
setInterval(tickWall, 500);

function connect() {
  const ws = new WebSocket(wsUrl(`/ws/episodes/${encodeURIComponent(id)}`));
  ws.binaryType = 'arraybuffer';
  ws.onmessage = (m) => {
    if (typeof m.data === 'string') onEvent(JSON.parse(m.data)); else showFrame(m.data);
  };
  ws.onclose = () => {
    if (budget.running) { $('state').textContent = 'reconnecting'; setTimeout(connect, 2000); }
  };
  ws.onopen = () => { $('calls').replaceChildren(); $('stages').replaceChildren(); $('agent').replaceChildren(); };
}

/** The operator's end of an episode (Finish and judge, Abort): the answer under the buttons. */
function showEnd(kind, text) {
  const out = $('end-result');
  out.className = kind;
  out.textContent = text;
}

$('finish').onclick = async () => {
  if (!confirm(`Finish ${id} now and judge it?`)) return;
  showEnd('muted', 'finishing …');
  const v = await finishEpisode(id);
  showEnd(v.success ? 'ok' : 'error', `judged: ${verdictText(v)}`);
};
$('abort').onclick = async () => {
  const reason = prompt(`Abort ${id}? The reason is kept in its record.`, 'aborted by the operator (live page)');
  if (reason === null || !reason.trim()) return;
  showEnd('muted', 'aborting …');
  const r = await abortEpisode(id, reason);
  showEnd(r.ok === false ? 'error' : 'muted', r.ok === false ? `not aborted: ${r.error}` : `aborted: ${reason}`);
};

connect();
