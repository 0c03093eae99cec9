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

/** Human text of a private evaluator event. */
export function stageText(e) {
  const what = (e.kind || 'event').replaceAll('_', ' ');
  const name = e.stage_name ? ` ${e.stage_name}` : '';
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
