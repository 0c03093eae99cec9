// Demos page: the library's bundles (task, verified, actions, date), play one's head | wrist video, verify by
// replay, delete, and export the selected ones to a LeRobot v3 dataset. Actions are same-origin POSTs.
import { el, postJson } from './common.js';

const $ = (x) => document.getElementById(x);
const status = (t) => { $('status').textContent = t; };

/** One line per configuration the bundle was replay-checked in (stages earned directly and after an offset). */
function checks(lines) {
  if (!lines || lines.length === 0) return '–';
  const box = el('div', { class: 'replay-checks' });
  for (const l of lines) box.append(el('div', { class: l.endsWith('refused') ? 'refused' : 'shown' }, l));
  return box;
}

function row(b) {
  const [task, bundle] = b.key.split('/');
  const tr = el('tr', { 'data-key': b.key });
  const pick = el('input', { type: 'checkbox', class: 'pick', value: b.key });
  const date = b.modified_unix_s ? new Date(b.modified_unix_s * 1000).toISOString().replace('T', ' ').slice(0, 19) : '–';
  const source = el('span', {}, b.source_type ?? '');
  if (b.episode_id) {
    // the source episode by id; linked to its review once the store says it knows it (linkSources)
    source.append(el('br'), el('small', { class: 'muted source-episode', 'data-episode': b.episode_id, title: 'not in this server\'s store' }, b.episode_id));
  }
  // A bundle recorded from a branch: its parent and step, and how many of the parent's actions are replayed
  // before its own trajectory (issue 49).
  const br = b.branch;
  if (br && br.parent_episode_id) {
    const note = el('small', { class: 'branch-of muted' }, 'branch of ');
    note.append(el('a', { href: `/episodes/${encodeURIComponent(br.parent_episode_id)}/review?step=${br.parent_control_step ?? 0}` }, br.parent_episode_id),
      ` at step ${br.parent_control_step ?? '?'}${br.replayed_actions != null ? ` (${br.replayed_actions} actions replayed first)` : ''}`);
    source.append(el('br'), note);
  }
  const cells = [pick, b.task ?? task, bundle, source, b.verified ? 'yes' : 'no',
    b.valid ? 'yes' : `no: ${b.first_violation}`, String(b.actions ?? '–'), checks(b.replay_checks), date];
  for (const c of cells) {
    const td = el('td');
    td.append(c);
    tr.append(td);
  }
  tr.children[4].className = b.verified ? 'outcome SUCCESS verified' : 'outcome FAIL verified';
  const actions = el('td');
  const play = el('button', { class: 'play' }, 'Play');
  play.onclick = () => {
    $('player').classList.remove('hidden');
    $('player-title').textContent = b.key;
    $('video').src = `/demos/${task}/${bundle}/video.mp4`;
    $('video').play().catch(() => {});
  };
  const verify = el('button', { class: 'verify' }, 'Verify');
  verify.onclick = async () => {
    status(`replaying ${b.key} …`);
    const r = await postJson(`/api/demos/${task}/${bundle}/verify`);
    status(r.ok ? `${b.key}: ${r.verified ? 'verified' : `not verified — ${r.reason}`}` : `verify failed: ${r.error}`);
    await load();
  };
  const del = el('button', { class: 'delete' }, 'Delete');
  del.onclick = async () => {
    if (!window.confirm(`Delete ${b.key}?`)) return;
    const r = await postJson(`/api/demos/${task}/${bundle}/delete`);
    status(r.ok ? `deleted ${b.key}` : `delete failed: ${r.error}`);
    await load();
  };
  actions.append(play, ' ', verify, ' ', del);
  tr.append(actions);
  return tr;
}

/** Links each source episode the store knows to its review (a few lookups at a time); the others stay plain ids. */
async function linkSources() {
  const ids = [...new Set([...document.querySelectorAll('small.source-episode')].map((s) => s.dataset.episode))];
  const known = async (id) => (await fetch(`/api/episodes/${encodeURIComponent(id)}`)).ok;
  for (let i = 0; i < ids.length; i += 4) {
    const part = ids.slice(i, i + 4);
    const found = await Promise.all(part.map((id) => known(id).catch(() => false)));
    part.forEach((id, k) => {
      if (!found[k]) return;
      for (const s of document.querySelectorAll(`small.source-episode[data-episode="${CSS.escape(id)}"]`)) {
        s.replaceWith(el('a', { class: 'source-episode', href: `/episodes/${encodeURIComponent(id)}/review` }, id));
      }
    });
  }
}

async function load() {
  const r = await fetch('/api/demos').then((x) => x.json());
  if (!r.ok) { status(r.error); return; }
  $('bundles').replaceChildren(...r.bundles.map(row));
  if (!r.bundles.length) $('bundles').append(el('tr', {}, 'No bundles yet: record one from a task\'s Teleoperate page.'));
  await linkSources();
}

$('all').onchange = () => { for (const c of document.querySelectorAll('.pick')) c.checked = $('all').checked; };
$('export').onclick = async () => {
  const bundles = [...document.querySelectorAll('.pick:checked')].map((c) => c.value);
  if (!bundles.length) { status('select at least one bundle'); return; }
  status(`exporting ${bundles.length} bundle(s) …`);
  const r = await postJson('/api/demos/export', { bundles });
  status(r.ok ? `exported ${r.episodes} episode(s), ${r.frames} frames to ${r.out}` : `export failed: ${r.error}`);
};
load();
