// A teleop branch keeps what the robot holds (issue 49, item 3) with Debian's chromium (headless,
// playwright-core): opens /teleop/TASK?branch=PARENT&step=STEP at a step where the parent holds an object lifted,
// checks the page starts with the gripper closed (the parent's last command) before any input, drives up with `r`
// (no gripper key), then saves the demonstration and follows its verification: the page shows the replay's
// progress and no verdict badge before the result.
// Usage: node teleop_branch_hold_check.cjs BASE TASK PARENT STEP ARTIFACTS
// Prints one JSON line {"ok":true, "episode_id":"ep-…", "bundle":"T07/ep-…", ...}. Screenshots go to ARTIFACTS.
const { shotter, check, text, runChecks } = require('./common.cjs');

const [base, task, parent, step, artifacts] = process.argv.slice(2);
const shot = shotter(artifacts);

runChecks(base, async (context, report, errors) => {
  const page = await context.newPage();
  page.on('pageerror', (e) => errors.push(`teleop: ${e}`));
  await page.goto(`${base}/teleop/${task}?branch=${parent}&step=${step}`);
  report.gripper_before_input = await text(page, '#gripper');
  report.branch_note = await text(page, '.branch-of');
  check(report.gripper_before_input === 'closed', `a branch of a closed gripper starts closed (${report.gripper_before_input})`);
  check(/gripper closed/.test(report.branch_note), `the page says so (${report.branch_note})`);
  // Before any input the page shows where every episode here starts: the parent's moment at the branch step.
  const preview = page.locator('#preview img.pair');
  await page.waitForFunction(() => document.querySelector('#preview img.pair')?.naturalWidth > 0, null, { timeout: 180000 });
  report.preview_px = await preview.evaluate((img) => [img.naturalWidth, img.naturalHeight]);
  check(report.preview_px[0] === 512 && report.preview_px[1] === 256, `a head | wrist picture of the branch point before any input (${report.preview_px})`);
  await shot(page, 'branch-hold-before-input');
  await page.locator('.teleop').focus();
  await page.keyboard.down('r');
  await page.locator('#state', { hasText: 'driving' }).waitFor({ timeout: 180000 });
  await page.waitForTimeout(1500);
  await page.keyboard.up('r');
  await page.waitForFunction(() => Number(document.getElementById('acked').textContent) >= 10, null, { timeout: 60000 });
  await page.waitForTimeout(1000);
  report.episode_id = await text(page, '#episode');
  report.gripper_after = await text(page, '#gripper');
  report.acked = Number(await text(page, '#acked'));
  report.frame_step = await text(page, '#frame-step');
  check(report.gripper_after === 'closed', `still closed after driving (${report.gripper_after})`);
  await shot(page, 'branch-hold-driving');

  // Save: the badge reads saving/verifying (never the verdict) and the replay's frames count up, then the result.
  await page.evaluate(() => {
    window.__states = [];
    new MutationObserver(() => window.__states.push(document.getElementById('state').textContent))
      .observe(document.getElementById('state'), { childList: true, characterData: true, subtree: true });
  });
  await page.locator('#save').click();
  await page.locator('#save-progress').waitFor({ timeout: 120000 });
  report.progress_text = await text(page, '#save-result');
  check(/verifying it by replay: frame \d+ \/ \d+/.test(report.progress_text), `verification progress (${report.progress_text})`);
  await shot(page, 'branch-hold-verifying');
  await page.locator('#state', { hasText: /^(saved|save failed)$/ }).waitFor({ timeout: 600000 });
  report.states_while_saving = await page.evaluate(() => window.__states);
  const early = report.states_while_saving.slice(0, -1).filter((x) => /SUCCESS|FAIL|INVALID/.test(x));
  check(early.length === 0, `no verdict badge before the result: ${report.states_while_saving.join(' → ')}`);
  const result = page.locator('#save-result');
  report.save_text = await result.innerText();
  report.bundle = await result.getAttribute('data-bundle');
  report.verified = (await result.getAttribute('data-verified')) === 'true';
  check(report.bundle, `saved: ${report.save_text}`);
  check(report.save_text.includes(`replayed actions of ${parent}`), `the result names the replayed prefix (${report.save_text})`);
  await shot(page, 'branch-hold-saved');

  // The Demonstrations page names the bundle's parent, step and replayed prefix.
  await page.goto(`${base}/demos`);
  const row = page.locator(`tr[data-key="${report.bundle}"]`);
  await row.waitFor({ timeout: 60000 });
  report.demos_branch = await row.locator('small.branch-of').innerText();
  check(report.demos_branch.includes(parent) && report.demos_branch.includes(`at step ${step}`) && report.demos_branch.includes(`${step} actions replayed first`),
    `the Demonstrations page names the branch (${report.demos_branch})`);
  await shot(page, 'branch-hold-demos');
});
