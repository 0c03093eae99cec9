// The review page's "Continue from here" (issue 33) with Debian's chromium (headless, playwright-core): opens
// EPISODE's review, steps STEPS control steps forward with → from its start, clicks "by teleop", follows the teleop
// page the control opens (its first key makes the branch) until it drives and shows frames, and reads the branch's episode id.
// Prints one JSON line {"ok":true, "episode_id":"ep-…", "step":N, ...}. Screenshots go to ARTIFACTS.
const { launch, say, shotter, check, text, login } = require('./common.cjs');

const [base, episode, steps, artifacts] = process.argv.slice(2);
const shot = shotter(artifacts);

async function main() {
  const browser = await launch();
  const context = await browser.newContext({ viewport: { width: 1500, height: 1100 } });
  await login(context, base);
  const report = {};
  const errors = [];
  try {
    const page = await context.newPage();
    page.on('pageerror', (e) => errors.push(`review: ${e}`));
    await page.goto(`${base}/episodes/${episode}/review`);
    await page.waitForFunction(() => document.body.dataset.ready === 'true', null, { timeout: 120000 });
    await page.waitForFunction(() => document.getElementById('video').readyState >= 1, null, { timeout: 120000 });
    // from the first control step on, → moves one control step
    await page.waitForFunction(() => /^\d+$/.test(document.getElementById('cstep').textContent) || document.getElementById('cstep').textContent === 'settle', null, { timeout: 30000 });
    for (let i = 0; i < 40 && (await text(page, '#cstep')) !== steps; i++) {
      await page.keyboard.press('ArrowRight');
      await page.waitForTimeout(150);
    }
    report.review_step = await text(page, '#cstep');
    check(report.review_step === steps, `the review shows control step ${steps} (${report.review_step})`);
    report.continue_step = await text(page, '#continue-step');
    check(report.continue_step === steps, `"Continue from here" offers step ${steps} (${report.continue_step})`);
    await shot(page, 'branch-review');
    // "prepare for an agent" prints a command that works: this server's binary by its path
    await page.locator('#continue-agent').click();
    await page.locator('#continue-command').waitFor({ timeout: 60000 });
    report.agent_command = await text(page, '#continue-command');
    check(/^\/\S*libero-agent agent --workspace '\//.test(report.agent_command), `the agent command names the binary's path (${report.agent_command})`);
    await page.locator('#continue-teleop').click();
    await page.waitForURL(`**/teleop/**branch=${episode}**`, { timeout: 30000 });
    page.on('pageerror', (e) => errors.push(`teleop: ${e}`));
    // The page makes the branch on the first input (issue 49): a key press starts it.
    await page.locator('#state', { hasText: 'ready' }).waitFor({ timeout: 30000 });
    await page.locator('.teleop').focus();
    await page.keyboard.press('r');
    await page.locator('#state', { hasText: 'driving' }).waitFor({ timeout: 180000 });
    await page.waitForFunction(() => Number(document.getElementById('frame-count').textContent) >= 1, null, { timeout: 120000 });
    report.episode_id = await text(page, '#episode');
    report.branch_note = await text(page, '.branch-of');
    report.frame_step = await text(page, '#frame-step');
    check(report.branch_note.includes(episode) && report.branch_note.includes(`step ${steps}`), `the teleop page says it is a branch (${report.branch_note})`);
    await shot(page, 'branch-teleop');
    report.step = Number(steps);
    check(errors.length === 0, `page errors: ${errors.join('; ')}`);
    report.ok = true;
  } catch (e) {
    report.ok = false;
    report.error = String(e && e.stack ? e.stack : e);
    report.errors = errors;
  } finally {
    await browser.close();
  }
  say(report);
  process.exit(report.ok ? 0 : 1);
}

main();
