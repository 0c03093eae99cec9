// Review page, stage annotation (issue 48): every required stage of a batch's long-horizon rollout with its
// automatic label, pre-filled and marked "automatic" until a person saves it (reached, succeeded, failure modes,
// note). Keyboard: j/k stage, r reached, s succeeded, 1–4 modes, n note (Esc leaves it), Enter saves the stage and
// goes to the next, c saves every stage not yet annotated as shown, ] / [ next / previous episode of the batch.
import { el, postJson, stageLabel } from './common.js';

const $ = (x) => document.getElementById(x);
const box = $('annotate');
const episode = box?.dataset.episode;
let data = null;
let current = 0;

const who = () => ($('annotator').value || '').trim();
const status = (t, bad = false) => { $('annotate-status').textContent = t; $('annotate-status').className = bad ? 'bad' : 'muted'; };

function modeText(modes) {
  if (!modes || modes.length === 0) return '';
  return modes.map((m) => data.modes.find((x) => x.key === m)?.label ?? m).join(' + ');
}

function autoText(a) {
  if (a.succeeded) return 'succeeded';
  if (!a.reached) return 'not reached';
  return `failed${a.failure_modes.length ? `: ${modeText(a.failure_modes)}` : ''}`;
}

/** The form's values of stage row `tr`. */
function values(tr) {
  const q = (name) => tr.querySelector(`[name="${name}"]`);
  return {
    stage_name: tr.dataset.stage,
    reached: q('reached').checked,
    succeeded: q('succeeded').checked,
    failure_modes: data.modes.filter((m) => q(m.key).checked).map((m) => m.key),
    note: q('note').value,
    annotator: who(),
  };
}

/** Modes only mean something on a reached stage that did not succeed. */
function syncEnabled(tr) {
  const v = values(tr);
  for (const m of data.modes) tr.querySelector(`[name="${m.key}"]`).disabled = !v.reached || v.succeeded;
}

function stageRow(s, i) {
  const shown = s.annotation ?? s.automatic;
  const tr = el('tr', { 'data-stage': s.stage_name, 'data-i': String(i), class: s.annotation ? 'annotated' : 'automatic' });
  const check = (name, on, title) => {
    const input = el('input', { type: 'checkbox', name, title });
    input.checked = on;
    input.addEventListener('change', () => { syncEnabled(tr); tr.classList.add('dirty'); });
    return input;
  };
  const cells = [
    el('td', { title: s.stage_name }, stageLabel(s.stage_name)),
    el('td', { class: 'muted' }, s.stage_type ? s.stage_type.replaceAll('_', ' ') : '–'),
    el('td', { class: 'auto' }, autoText(s.automatic)),
  ];
  const tdR = el('td'); tdR.append(check('reached', shown.reached || shown.succeeded, 'reached (r)'));
  const tdS = el('td'); tdS.append(check('succeeded', shown.succeeded, 'succeeded (s)'));
  const tdM = el('td', { class: 'modes' });
  data.modes.forEach((m, k) => {
    const label = el('label', { title: `${m.label} (${k + 1})` });
    label.append(check(m.key, shown.failure_modes.includes(m.key), `${m.label} (${k + 1})`), ` ${k + 1} ${m.label}`);
    tdM.append(label);
  });
  const note = el('input', { type: 'text', name: 'note', maxlength: '2000', placeholder: 'note (n)', value: s.annotation?.note ?? '' });
  note.addEventListener('input', () => tr.classList.add('dirty'));
  const tdN = el('td'); tdN.append(note);
  const state = el('td', { class: 'who' }, s.annotation ? `${s.annotation.annotator}, ${s.annotation.annotated_at.slice(0, 16).replace('T', ' ')}` : 'automatic, not confirmed');
  const save = el('button', { type: 'button', class: 'save-stage', title: 'save (Enter)' }, 'save');
  save.addEventListener('click', () => saveStage(i));
  const tdB = el('td'); tdB.append(save);
  tr.append(...cells, tdR, tdS, tdM, tdN, state, tdB);
  tr.addEventListener('click', (e) => { if (!(e.target instanceof HTMLInputElement) && e.target !== save) select(i); });
  syncEnabled(tr);
  return tr;
}

function rows() { return [...$('annotate-stages').querySelectorAll('tr[data-stage]')]; }

function select(i) {
  const all = rows();
  if (all.length === 0) return;
  current = Math.max(0, Math.min(all.length - 1, i));
  all.forEach((tr, k) => tr.classList.toggle('current', k === current));
}

async function saveStage(i, { advance = false } = {}) {
  const tr = rows()[i];
  if (!tr) return false;
  if (!who()) { status('enter your name first (it is stored with every annotation)', true); $('annotator').focus(); return false; }
  localStorage.setItem('libero.annotator', who());
  const r = await postJson(`/api/episodes/${episode}/stages`, values(tr));
  if (!r.ok) { status(`${tr.dataset.stage}: ${r.error}`, true); return false; }
  data.stages[i].annotation = r.annotation;
  tr.replaceWith(stageRow(data.stages[i], i));
  select(advance ? i + 1 : i);
  summary();
  status(`saved ${r.stage_name}`);
  return true;
}

async function confirmRest() {
  for (let i = 0; i < data.stages.length; i++) {
    if (!data.stages[i].annotation && !(await saveStage(i))) return;
  }
  status('every stage annotated');
}

function summary() {
  const n = data.stages.length;
  const done = data.stages.filter((s) => s.annotation).length;
  $('annotate-count').textContent = `${done} of ${n} stages annotated${data.in_table4 ? '' : ' (this task is not in the paper\'s Table 4, only in Table 4+)'}`;
}

function nav() {
  const go = (id) => (id ? `/episodes/${id}/review#annotate` : null);
  const links = $('annotate-nav');
  links.replaceChildren();
  const link = (id, text, key) => {
    const a = id ? el('a', { href: go(id), id: key }, text) : el('span', { class: 'muted' }, text);
    links.append(a, ' ');
  };
  link(data.previous, '◀ previous episode ([)', 'annotate-prev');
  links.append(el('span', { class: 'muted' }, `episode ${data.position ?? '?'} of ${data.episodes} long-horizon rollouts of batch ${data.batch}`), ' ');
  link(data.next, 'next episode (]) ▶', 'annotate-next');
}

async function load() {
  if (!box) return;
  $('annotator').value = localStorage.getItem('libero.annotator') || '';
  const r = await fetch(`/api/episodes/${episode}/stages`).then((x) => x.json()).catch((e) => ({ ok: false, error: String(e) }));
  if (!r.ok) { box.classList.add('unavailable'); status(r.error, false); return; }
  data = r;
  const body = $('annotate-stages');
  body.replaceChildren(...data.stages.map(stageRow));
  select(0);
  summary();
  nav();
  box.classList.remove('hidden');
  if (location.hash === '#annotate') box.scrollIntoView();
}

function toggle(name) {
  const tr = rows()[current];
  const input = tr?.querySelector(`[name="${name}"]`);
  if (!input || input.disabled) return;
  input.checked = !input.checked;
  input.dispatchEvent(new Event('change'));
}

document.addEventListener('keydown', (e) => {
  if (!data || e.ctrlKey || e.metaKey || e.altKey) return;
  const t = e.target;
  if (t instanceof HTMLInputElement && t.type === 'text') {
    if (e.key === 'Escape') t.blur();
    if (e.key === 'Enter' && t.name === 'note') { e.preventDefault(); t.blur(); saveStage(current, { advance: true }); }
    return;
  }
  const key = e.key;
  const act = {
    j: () => select(current + 1), k: () => select(current - 1),
    r: () => toggle('reached'), s: () => toggle('succeeded'),
    n: () => rows()[current]?.querySelector('[name="note"]').focus(),
    Enter: () => saveStage(current, { advance: true }),
    c: () => confirmRest(),
    ']': () => { if (data.next) location.href = `/episodes/${data.next}/review#annotate`; },
    '[': () => { if (data.previous) location.href = `/episodes/${data.previous}/review#annotate`; },
  };
  const mode = Number.parseInt(key, 10);
  if (mode >= 1 && mode <= data.modes.length) { e.preventDefault(); toggle(data.modes[mode - 1].key); return; }
  if (act[key]) { e.preventDefault(); act[key](); }
});

load();
