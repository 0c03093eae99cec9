// The page of an episode another server of the shared store runs: the store's row, pushed over
// /ws/episodes/{id} whenever the store changes (PostgreSQL LISTEN/NOTIFY), until the episode ends; then the
// review opens. Without the socket the page falls back to reloading every 5 s.
import { wsUrl } from '/static/common.js';

const root = document.querySelector('[data-episode]');
const id = root.dataset.episode;
const note = document.getElementById('follow-note');
let ended = false;

function set(elementId, text) {
  const e = document.getElementById(elementId);
  if (e && typeof text === 'string') e.textContent = text;
}

function reloadSoon() {
  if (ended) return;
  note.textContent = 'Lost the live connection to this dashboard; reloading in 5 s.';
  setTimeout(() => location.reload(), 5000);
}

const ws = new WebSocket(wsUrl(`/ws/episodes/${encodeURIComponent(id)}`));
ws.onmessage = (ev) => {
  if (typeof ev.data !== 'string') return;
  const m = JSON.parse(ev.data);
  if (m.type === 'elsewhere') {
    set('state', m.state);
    set('started', m.started_at || 'not yet');
    set('steps', m.steps);
    set('stages', m.stages);
    note.textContent = `Following the shared store: updated ${new Date().toLocaleTimeString()}.`;
  } else if (m.type === 'ended') {
    ended = true;
    set('state', `ended: ${m.outcome}`);
    note.textContent = 'The episode ended; opening its review.';
    location.assign(m.review_url);
  } else if (m.type === 'finished') {
    // This server runs it after all (or it ended before this page connected): the review has it.
    ended = true;
    location.assign(`/episodes/${encodeURIComponent(id)}/review`);
  }
};
ws.onclose = reloadSoon;
