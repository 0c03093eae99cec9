// The review of an episode without a private video (issue 49, item 1), with Debian's chromium (headless,
// playwright-core): opens EPISODE's review at the moment of control step STEP (its `?t=` link), and checks that the
// page shows moments rendered from the recorded state (an image per control step, not "no video"), that the plots
// have their telemetry, that ← / → step one control step and the image follows, that play advances, and that
// "Continue from here" prepares a branch at the step shown. Prints one JSON line; screenshots go to ARTIFACTS.
const { shotter, check, text, runChecks } = require('./common.cjs');

const [base, episode, stepArg, artifacts] = process.argv.slice(2);
const shot = shotter(artifacts);
const step = Number(stepArg);

/** Distinct colours in a canvas's plot area: a drawn plot has many, an empty one a handful. */
function plotColours(page, id) {
  return page.evaluate((canvasId) => {
    const c = document.getElementById(canvasId);
    const d = c.getContext('2d').getImageData(0, 20, c.width, c.height - 40).data;
    const seen = new Set();
    for (let i = 0; i < d.length; i += 4 * 7) seen.add(`${d[i]},${d[i + 1]},${d[i + 2]},${d[i + 3]}`);
    return seen.size;
  }, id);
}

/** The control step the moment image shows, once it has loaded. */
async function shownStep(page, expected) {
  await page.waitForFunction((want) => {
    const img = document.getElementById('moment');
    return img && img.dataset.step === String(want) && img.complete && img.naturalWidth > 0 && !img.hasAttribute('aria-busy');
  }, expected, { timeout: 180000 });
  return page.evaluate(() => ({ step: Number(document.getElementById('moment').dataset.step), width: document.getElementById('moment').naturalWidth }));
}

runChecks(base, async (context, report, errors) => {
    const page = await context.newPage();
    page.on('pageerror', (e) => errors.push(`review: ${e}`));
    const t = ((step + 0.5) / 20).toFixed(3);
    const t0 = Date.now();
    await page.goto(`${base}/episodes/${episode}/review?t=${t}`);
    await page.waitForFunction(() => document.body.dataset.ready === 'true', null, { timeout: 120000 });
    report.player = await page.evaluate(() => document.body.dataset.player ?? 'video');
    check(report.player === 'moments', `the review plays moments from the recorded state (${report.player})`);
    report.note = await text(page, '#video-status');
    check(/rendered from the recorded state/.test(report.note), `the page says where its images come from (${report.note})`);
    const first = await shownStep(page, step);
    report.first_moment_ms = Date.now() - t0;
    check(first.width === 512, `the moment is head | wrist at 512×256 (${first.width})`);
    report.cstep = await text(page, '#cstep');
    check(report.cstep === String(step), `the deep link opens control step ${step} (${report.cstep})`);
    report.time = await text(page, '#time');
    check(report.time !== '0.00', `the moment has its time (${report.time})`);
    // The moment is what the agent saw: at the end of the last call, its head half matches that call's observation
    // image (JPEG against PNG: a few levels apart), and not the start's.
    report.fidelity = await page.evaluate(async (ep) => {
      const review = await (await fetch(`/api/episodes/${ep}/review`)).json();
      const observed = review.calls.filter((c) => c.ok && typeof c.observation_id === 'string');
      const [start, last] = [observed[0], observed[observed.length - 1]];
      const load = (src) => new Promise((resolve, reject) => { const i = new Image(); i.onload = () => resolve(i); i.onerror = () => reject(new Error(src)); i.src = src; });
      const pixels = (img) => {
        const c = document.createElement('canvas'); c.width = 256; c.height = 256;
        const g = c.getContext('2d'); g.drawImage(img, 0, 0, 256, 256, 0, 0, 256, 256);
        return g.getImageData(0, 0, 256, 256).data;
      };
      const diff = (a, b) => { let sum = 0; for (let i = 0; i < a.length; i += 4) sum += Math.abs(a[i] - b[i]) + Math.abs(a[i + 1] - b[i + 1]) + Math.abs(a[i + 2] - b[i + 2]); return sum / (256 * 256 * 3); };
      const moment = pixels(await load(`/api/episodes/${ep}/moment?step=${last.control_step_end}`));
      const head = (call) => load(`/episodes/${ep}/observations/${call.observation_id}/head/rgb.png`).then(pixels);
      return { step: last.control_step_end, same_state: diff(moment, await head(last)), start_state: diff(moment, await head(start)) };
    }, episode);
    check(report.fidelity.same_state < 4 && report.fidelity.start_state > 3 * report.fidelity.same_state,
      `the moment shows the state the agent observed (${JSON.stringify(report.fidelity)})`);
    report.plot_colours = await plotColours(page, 'plot-eef');
    check(report.plot_colours > 8, `the end-effector plot is drawn from the telemetry (${report.plot_colours} colours)`);
    const events = await page.$$eval('#events li', (lis) => lis.map((li) => li.textContent));
    report.timeline_rows = events.length;
    check(events.length > 0 && events.every((e) => !e.startsWith('– s')), `timeline rows have times (${events.slice(0, 3).join(' | ')})`);
    const before = await page.evaluate(() => document.getElementById('moment').src);
    await page.keyboard.press('ArrowRight');
    const next = await shownStep(page, step + 1);
    report.after_right = next.step;
    check(await page.evaluate((b) => document.getElementById('moment').src !== b, before), '→ shows a new image');
    await page.keyboard.press('ArrowLeft');
    await page.keyboard.press('ArrowLeft');
    report.after_left = (await shownStep(page, step - 1)).step;
    check((await text(page, '#continue-step')) === String(step - 1), '"Continue from here" follows the moment shown');
    await shot(page, 'review-moments');
    // play for a while: the moment advances at the episode's pace (as many moments as the renderer allows)
    await page.locator('#play').click();
    await page.waitForTimeout(2000);
    await page.locator('#play').click();
    report.after_play = Number(await text(page, '#cstep'));
    check(report.after_play > step, `play advances the moment (${report.after_play})`);
    report.moments_while_playing = await page.evaluate(() => performance.getEntriesByType('resource').filter((r) => r.name.includes('/moment?step=')).length);
    // continue from the moment shown, for an agent
    await page.keyboard.press('ArrowLeft');
    const branchStep = Number(await text(page, '#cstep'));
    await page.locator('#continue-agent').click();
    await page.locator('#continue-command').waitFor({ timeout: 120000 });
    report.branch_text = await text(page, '#continue-result');
    check(report.branch_text.includes(`at step ${branchStep}`), `the branch is prepared at step ${branchStep} (${report.branch_text.slice(0, 120)})`);
    check(report.branch_text.includes('harness expert, model solve, no batch'), `the branch names its harness and model, the parent's (${report.branch_text.slice(0, 160)})`);
    report.branch_step = branchStep;
    await shot(page, 'review-moments-branch');
});
