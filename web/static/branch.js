// Review page, "Continue from here" (issue 33): a new episode that starts from this episode's state at the control
// step the review shows (its actions replayed to there), driven by teleop (the teleop page makes the branch) or
// prepared for an agent (`POST /api/episodes {branch}`: its own MCP endpoint and workspace, shown here).
import { el, postJson } from './common.js';

const box = document.getElementById('continue');
const $ = (x) => document.getElementById(x);

/** The control step the review shows now: the settle frames before the start are step 0. */
function currentStep() {
  const text = $('cstep')?.textContent ?? '';
  const n = Number(text);
  return Number.isInteger(n) && n >= 0 && text.trim() !== '' ? n : 0;
}

function show(...children) {
  const out = $('continue-result');
  out.replaceChildren(...children);
  out.classList.remove('hidden');
}

function showStep() { $('continue-step').textContent = String(currentStep()); }

if (box) {
  const parent = box.dataset.episode;
  const task = box.dataset.task;
  // the label follows the review's step (video play, scrubbing, keys)
  new MutationObserver(showStep).observe($('cstep'), { childList: true, characterData: true, subtree: true });
  showStep();
  $('continue-teleop').addEventListener('click', () => {
    const q = new URLSearchParams({ branch: parent, step: String(currentStep()) });
    location.href = `/teleop/${task.split('/').map(encodeURIComponent).join('/')}?${q}`;
  });
  $('continue-agent').addEventListener('click', async (ev) => {
    const button = ev.currentTarget;
    button.disabled = true;
    const step = currentStep();
    // Recorded with the harness and model asked for (the parent's by default); never in a batch, so a branch does not
    // count toward the parent batch's results.
    const named = (input) => { const v = $(input).value.trim(); return v === '' ? undefined : v; };
    const [harness, model] = [named('continue-harness'), named('continue-model')];
    const r = await postJson('/api/episodes', { branch: { parent, step }, level: Number(box.dataset.level), harness, model });
    button.disabled = false;
    if (!r.ok && !r.episode_id) { show(el('p', { class: 'error' }, `cannot branch: ${r.error}`)); return; }
    const config = { mcpServers: { libero: { type: 'http', url: r.mcp_url, headers: r.mcp_headers } } };
    const pre = (text, id) => el('pre', { id }, text);
    show(
      el('p', {}, `Prepared branch ${r.episode_id} at step ${step} (harness ${harness ?? '–'}, model ${model ?? '–'}, no batch): `),
      el('a', { id: 'continue-live', href: `/episodes/${encodeURIComponent(r.episode_id)}` }, 'its live view'),
      el('p', {}, 'Workspace'), pre(r.workspace, 'continue-workspace'),
      el('p', {}, 'MCP URL'), pre(r.mcp_url, 'continue-mcp-url'),
      el('p', {}, 'Run the reference agent into it'), pre(`${box.dataset.exe || 'libero-agent'} agent --workspace '${r.workspace}'`, 'continue-command'),
      el('p', {}, 'or give an agent this MCP configuration'), pre(JSON.stringify(config, null, 2), 'continue-mcp-config'),
    );
  });
}
