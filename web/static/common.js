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
