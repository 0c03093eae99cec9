// Shared helpers of the dashboard's pages (vanilla ES modules, no build step).

/** The WebSocket URL of a server path, on the page's own host and scheme. */
export function wsUrl(path) {
  const scheme = location.protocol === 'https:' ? 'wss:' : 'ws:';
  return `${scheme}//${location.host}${path}`;
}

/** A new element with attributes and text. */
export function el(tag, attrs = {}, text = '') {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (v !== undefined && v !== null) e.setAttribute(k, v);
  }
  if (text !== '') e.textContent = text;
  return e;
}

/** Seconds with a fixed number of decimals, or a dash. */
export function fmtS(s, digits = 2) {
  return typeof s === 'number' && Number.isFinite(s) ? s.toFixed(digits) : '–';
}

/** "3 actions" / "no arguments" summary of a call. */
export function callSummary(tool, actions) {
  return actions === null || actions === undefined ? tool : `${tool} (${actions} actions)`;
}

/**
 * A stage's name for people: `01_Moka_Pot_On_Second_Stove` → `1 · Moka pot on second stove` (the record's name stays
 * in the element's title where the caller sets it).
 */
export function stageLabel(name) {
  if (!name) return '';
  const m = /^(\d+)_(.*)$/.exec(name);
  const words = (m ? m[2] : name).replaceAll('_', ' ').trim().toLowerCase();
  const text = words.charAt(0).toUpperCase() + words.slice(1);
  return m ? `${Number(m[1])} · ${text}` : text;
}

/** Human text of a private evaluator event. */
export function stageText(e) {
  const what = (e.kind || 'event').replaceAll('_', ' ');
  const name = e.stage_name ? ` ${stageLabel(e.stage_name)}` : '';
  const subject = e.subject ? ` (${e.subject})` : '';
  return `${what}${name}${subject} @ step ${e.control_step}, ${fmtS(e.sim_time_s)} s`;
}

/** A binary frame message (4-byte LE header length, JSON header, JPEG) as {header, blob}. */
export function parseFrame(buf) {
  const n = new DataView(buf).getUint32(0, true);
  const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 4, n)));
  return { header, blob: new Blob([new Uint8Array(buf, 4 + n)], { type: 'image/jpeg' }) };
}

/** Shows a JPEG blob in `img`, releasing the previous object URL once the new one is drawn. */
export function showBlob(img, blob) {
  const old = img.src;
  img.onload = () => { if (old.startsWith('blob:')) URL.revokeObjectURL(old); };
  img.src = URL.createObjectURL(blob);
}

/** POSTs JSON (same-origin, so the cross-site guard lets it through) and returns the parsed answer. */
export async function postJson(path, body = {}) {
  const r = await fetch(path, { method: 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify(body) });
  const v = await r.json().catch(() => ({ ok: false, error: `HTTP ${r.status}` }));
  if (!r.ok && v.ok !== false) v.ok = false;
  return v;
}

/** Shows a private evaluator event (`stage` into the list, `progress` as c/K); false for any other event. */
export function showEvaluatorEvent(e, stages, progress) {
  if (e.type === 'stage') stages.prepend(el('li', { class: e.event.kind }, stageText(e.event)));
  else if (e.type === 'progress') progress.textContent = `${e.completed}/${e.required}`;
  else return false;
  return true;
}

/** One line of the agent's transcript (`agent_events.jsonl`, docs/agent_transcript.md) as short text. */
export function agentEventText(e) {
  const clip = (s, n = 240) => (s && s.length > n ? `${s.slice(0, n)}…` : s ?? '');
  switch (e.kind) {
    case 'message': return `says: ${clip(e.text)}`;
    case 'reasoning': return `thinks: ${clip(e.text)}`;
    case 'shell': return `$ ${clip(e.command, 160)}${e.exit_code != null ? ` → exit ${e.exit_code}` : e.is_error ? ' → failed' : ''}`;
    case 'file_read': return `reads ${e.workspace_path ?? e.path}`;
    case 'image_view': return `views ${e.workspace_path ?? e.path}`;
    case 'tool_call': return e.robot_tool
      ? `calls ${e.robot_tool}${e.observation_id ? ` on ${e.observation_id}` : ''}`
      : `calls ${e.tool} ${clip(e.arguments, 120)}`;
    case 'tool_result': return `${e.tool ?? 'tool'} → ${e.observation_id ?? ''} ${clip(e.text, 160)}`;
    case 'usage': {
      const t = e.tokens ?? {};
      const src = e.source === 'model_api_gateway' ? 'gateway' : 'as printed';
      return `tokens in ${t.input_tokens ?? '–'} (cached ${t.cached_input_tokens ?? '–'}) out ${t.output_tokens ?? '–'} (${src})`;
    }
    case 'stderr': return `stderr: ${clip(e.text)}`;
    default: return clip(e.text) || e.kind;
  }
}

/** A list item for a transcript event: its text, and for shell commands and results their bounded output. */
export function agentEventItem(e) {
  const li = el('li', { class: `agent ${e.kind}${e.is_error ? ' error' : ''}`, title: e.t ?? '' });
  const more = e.kind === 'shell' ? e.output : e.kind === 'tool_result' || e.kind === 'message' || e.kind === 'reasoning' ? e.text : null;
  if (more && more.length > 240) {
    const d = el('details');
    d.append(el('summary', {}, agentEventText(e)), el('pre', { class: 'state' }, more));
    li.append(d);
  } else {
    li.textContent = agentEventText(e);
    if (e.kind === 'shell' && e.output) li.append(el('pre', { class: 'state' }, e.output));
  }
  if (e.truncated) li.append(el('span', { class: 'muted' }, ' (cut)'));
  return li;
}

/** "SUCCESS · stages 1/1" (or why not) from `POST /api/episodes/{id}/finish`'s answer: the evaluator's verdict. */
export function verdictText(v) {
  if (!v.ok && !v.outcome) return `not judged: ${v.error ?? v.answer?.error ?? 'the episode could not finish'}`;
  const stages = v.required_stage_count != null ? ` · stages ${v.completed_required_stage_count ?? '?'}/${v.required_stage_count}` : '';
  const why = v.reason ? ` (${v.reason})` : '';
  return `${v.outcome ?? v.state}${stages}${why}`;
}

/** "Finish and judge": ends episode `id` with its own finish_episode; the answer carries the verdict. */
export function finishEpisode(id) {
  return postJson(`/api/episodes/${encodeURIComponent(id)}/finish`);
}

/** Aborts episode `id` with `reason` (ended as INVALID, the reason kept in its record). */
export function abortEpisode(id, reason) {
  return postJson(`/api/episodes/${encodeURIComponent(id)}/abort`, { reason });
}
