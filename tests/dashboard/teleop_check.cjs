// Drives the teleop page with Debian's chromium (headless, playwright-core): from the tasks page's Teleoperate link
// for TASK, starts the episode with a key, waits for live frames, holds `d` then `f` and taps space (robosuite 1.4 keys), checks that frames
// change, the control step advances, the latency and achieved-rate labels fill in, saves the demonstration and
// reads the verdict, then opens the Demos page (the bundle is listed, its video loads) and exports it to LeRobot.
// Prints one JSON line {"ok":true, "bundle":"T14/ep-…", ...}. Screenshots go to ARTIFACTS.
const { launch, say, shotter, check, text, login } = require('./common.cjs');

const [base, task, artifacts] = process.argv.slice(2);
const shot = shotter(artifacts);
const frameSrc = (page) => page.locator('#frame').evaluate((e) => e.src);

async function hold(page, key, ms) {
  await page.keyboard.down(key);
  await page.waitForTimeout(ms);
  await page.keyboard.up(key);
}

async function main() {
  const browser = await launch();
  const context = await browser.newContext({ viewport: { width: 1500, height: 1100 } });
  await login(context, base);
  const report = {};
  const errors = [];
  try {
    const page = await context.newPage();
    page.on('pageerror', (e) => errors.push(`teleop: ${e}`));
    await page.goto(`${base}/tasks`);
    await page.locator(`#${task} a.teleop-link`).click();
    await page.waitForURL(`**/teleop/${task}`);
    // The page makes its episode on the first input (issue 49): a key press starts it.
    await page.locator('#state', { hasText: 'ready' }).waitFor({ timeout: 30000 });
    await page.locator('.teleop').focus();
    await page.keyboard.press('d');
    await page.locator('#state', { hasText: 'driving' }).waitFor({ timeout: 180000 });
    await page.waitForFunction(() => Number(document.getElementById('frame-count').textContent) >= 2, null, { timeout: 120000 });
    const before = { src: await frameSrc(page), step: await text(page, '#frame-step') };
    await page.locator('.teleop').focus();
    await hold(page, 'd', 1500);
    await page.waitForFunction(() => document.getElementById('latency').textContent.endsWith('ms'), null, { timeout: 60000 });
    report.latency_d = await text(page, '#latency');
    await hold(page, 'f', 1200);
    await page.keyboard.press('Space');
    await page.waitForTimeout(1500);
    check((await text(page, '#gripper')) === 'closed', 'space closes the gripper');
    const after = { src: await frameSrc(page), step: await text(page, '#frame-step') };
    check(after.src !== before.src, 'the frame changed');
    const stepOf = (t) => (/^\d+$/.test(t) ? Number(t) : -1); // 'settle' / '–' before the first action
    check(stepOf(after.step) > stepOf(before.step), `control step advanced (${before.step} → ${after.step})`);
    report.latency = await text(page, '#latency');
    check(/^\d+ ms$/.test(report.latency), `latency label ${report.latency}`);
    report.rate_hz = Number(await text(page, '#rate'));
    check(report.rate_hz > 0, `achieved rate ${report.rate_hz}`);
    report.acked = Number(await text(page, '#acked'));
    report.frames = Number(await text(page, '#frame-count'));
    report.steps = { before: before.step, after: after.step };
    report.progress = await text(page, '#progress');
    await shot(page, 'teleop-driving');

    await page.locator('#save').click();
    // The replay that verifies the bundle shows its progress before the result.
    await page.locator('#save-progress').waitFor({ timeout: 300000 });
    report.save_progress = await text(page, '#save-result');
    await page.locator('#state', { hasText: /saved|save failed/ }).waitFor({ timeout: 300000 });
    const result = page.locator('#save-result');
    report.save_text = await result.innerText();
    report.bundle = await result.getAttribute('data-bundle');
    report.verified = (await result.getAttribute('data-verified')) === 'true';
    check(report.bundle, `saved: ${report.save_text}`);
    await shot(page, 'teleop-saved');

    const demos = await context.newPage();
    demos.on('pageerror', (e) => errors.push(`demos: ${e}`));
    await demos.goto(`${base}/demos`);
    const row = demos.locator(`tr[data-key="${report.bundle}"]`);
    await row.waitFor({ timeout: 15000 });
    await row.locator('button.play').click();
    await demos.waitForFunction(() => document.getElementById('video').readyState >= 1, null, { timeout: 30000 });
    report.video_duration_s = await demos.locator('#video').evaluate((v) => v.duration);
    await row.locator('input.pick').check();
    await demos.locator('#export').click();
    await demos.locator('#status', { hasText: /exported|failed/ }).waitFor({ timeout: 120000 });
    report.export = await text(demos, '#status');
    check(report.export.startsWith('exported 1 episode'), `export: ${report.export}`);
    await shot(demos, 'demos');
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
