// Home page: the episode table, replaced whenever the server pushes a changed list (filters travel in the URL).
import { wsUrl, el, fmtS } from './common.js';

const tbody = document.getElementById('episodes');
const status = document.getElementById('live-status');

/** An ending's reason cut to one line (the same cut as the server-rendered page: 80 characters). */
function shortReason(r) {
  const chars = [...r];
  return chars.length > 80 ? `${chars.slice(0, 79).join('')}…` : r;
}

function row(e) {
  const tr = el('tr', { 'data-id': e.id });
  // Open episodes go to the live page, ended ones straight to their review.
  const ended = e.outcome && e.outcome !== 'RUNNING';
  const link = el('a', { href: `/episodes/${encodeURIComponent(e.id)}${ended ? '/review' : ''}` }, e.id);
  // A branch names its parent and step (issue 33).
  const idCell = e.branch_parent ? el('span') : link;
  if (e.branch_parent) {
    const note = el('small', { class: 'branch-of muted' }, 'branch of ');
    note.append(el('a', { href: `/episodes/${encodeURIComponent(e.branch_parent)}/review` }, e.branch_parent), ` at step ${e.branch_step}`);
    idCell.append(link, el('br'), note);
  }
  const progress = e.completed_stage_count != null && e.required_stage_count != null
    ? `${e.completed_stage_count}/${e.required_stage_count}` : '–';
  // The batch links to this page filtered on it; times read as minutes in UTC, the record's timestamp on hover.
  const batch = e.batch ? el('a', { class: 'batch-link', href: `/?batch=${encodeURIComponent(e.batch)}` }, e.batch) : '';
  const startedIso = e.started_at ?? e.created_at ?? '';
  const started = el('time', { datetime: startedIso, title: startedIso },
    /^\d{4}-\d{2}-\d{2}T\d{2}:\d{2}/.test(startedIso) ? `${startedIso.slice(0, 10)} ${startedIso.slice(11, 16)} UTC` : startedIso);
  const cells = [
    idCell, e.task_ref, e.harness ?? '', e.model ?? '', batch, String(e.level),
    e.outcome ?? 'RUNNING', progress, e.wall_time_s != null ? `${fmtS(e.wall_time_s, 1)} s` : '–',
    e.accepted_agent_steps != null ? String(e.accepted_agent_steps) : '–', started,
  ];
  cells.forEach((c, i) => {
    const td = el('td', i === 6 ? { class: `outcome ${c}` } : {});
    if (c instanceof Node) td.append(c); else td.textContent = c;
    // why an episode ended the way it did (abandoned, aborted, the runner's classification), in full on hover
    if (i === 6 && e.reason) {
      td.title = e.reason;
      td.append(el('br'), el('small', { class: 'end-reason muted' }, shortReason(e.reason)));
    }
    tr.append(td);
  });
  return tr;
}

function render(episodes) {
  tbody.replaceChildren(...episodes.map(row));
  document.getElementById('empty')?.remove();
}

function connect() {
  const ws = new WebSocket(wsUrl(`/ws/episodes${location.search}`));
  ws.onopen = () => { status.textContent = 'live'; };
  ws.onmessage = (m) => {
    const d = JSON.parse(m.data);
    if (d.type === 'episodes') render(d.episodes);
  };
  ws.onclose = () => {
    status.textContent = 'reconnecting';
    setTimeout(connect, 2000);
  };
}

connect();

// Getting started: prepare an episode and show the MCP configuration an agent needs.
document.getElementById('prepare-episode')?.addEventListener('click', async (ev) => {
  const button = ev.currentTarget;
  button.disabled = true;
  button.textContent = 'Preparing…';
  try {
    const r = await fetch('/api/episodes', { method: 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify({ task: 'T14' }) });
    const p = await r.json();
    if (!r.ok) throw new Error(p.error || r.statusText);
    const config = { mcpServers: { libero: { type: 'http', url: p.mcp_url, headers: p.mcp_headers } } };
    document.getElementById('mcp-config').textContent = JSON.stringify(config, null, 2);
    document.getElementById('prepared-workspace').textContent = p.workspace;
    document.getElementById('prepared-prompt').textContent = p.prompt_file;
    document.getElementById('reference-agent').textContent = `${document.getElementById('getting-started').dataset.exe} agent --workspace '${p.workspace}'`;
    document.getElementById('prepared').hidden = false;
    button.textContent = `Prepared ${p.episode_id}`;
  } catch (err) {
    button.disabled = false;
    button.textContent = 'Prepare a T14 episode';
    button.after(el('p', { class: 'error' }, `cannot prepare: ${err.message}`));
  }
});
