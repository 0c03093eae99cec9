// Annotates the stages of a batch's long-horizon rollout in the review page by keyboard only, as a person
// annotating a whole batch does: name, r (reached), 3 (geometric error), n + note, Enter (save and next stage),
// c (save the rest as shown), ] (next episode). Usage: node annotate_check.cjs BASE EPISODE ARTIFACTS. Prints one
// JSON line, {"ok":true,...} or {"ok":false,"error":...}. Screenshots go to ARTIFACTS.
const { launch, say, shotter, check, login } = require('./common.cjs');

const [base, episode, artifacts] = process.argv.slice(2);
const shot = shotter(artifacts);

async function main() {
  const browser = await launch();
  const errors = [];
  try {
    const context = await browser.newContext({ viewport: { width: 1500, height: 1100 } });
    await login(context, base);
    const page = await context.newPage();
    page.on('pageerror', (e) => errors.push(`${page.url()}: ${e}`));
    await page.goto(`${base}/episodes/${episode}/review#annotate`);
    await page.waitForSelector('#annotate:not(.hidden) #annotate-stages tr[data-stage]', { timeout: 30000 });
    const rows = page.locator('#annotate-stages tr[data-stage]');
    const n = await rows.count();
    check(n >= 2, `one row per required stage (${n})`);
    check(await page.locator('#annotate-stages tr.automatic').count() === n, 'every stage starts automatic, not confirmed');
    // stage names read as words, the record's name on hover (here and in the Stages table)
    const cell = rows.nth(0).locator('td').first();
    check(/^1 · [A-Z][a-z]/.test(await cell.innerText()), `a stage name for people: ${await cell.innerText()}`);
    check(/^01_/.test(await cell.getAttribute('title')), 'the record name on hover');
    check(/^1 · /.test(await page.locator('#stages tbody tr td:nth-child(2)').first().innerText()), 'the Stages table too');
    check((await page.locator('#annotate-count').innerText()).startsWith(`0 of ${n}`), 'nothing annotated yet');
    await shot(page, 'annotate-start');
    // Saving before naming oneself is refused with a clear message.
    await page.locator('#annotate h2').click();
    await page.keyboard.press('Enter');
    await page.waitForFunction(() => document.getElementById('annotate-status').textContent.includes('enter your name'));
    await page.fill('#annotator', 'Ada Annotator');
    await page.locator('#annotate h2').click();
    // Stage 1: reached (r), geometric error (3), a note (n, type, Enter saves and moves to stage 2).
    const first = rows.nth(0);
    const reachedBefore = await first.locator('[name="reached"]').isChecked();
    await page.keyboard.press('r');
    if (reachedBefore) await page.keyboard.press('r');
    check(await first.locator('[name="reached"]').isChecked(), 'r toggles reached');
    await page.keyboard.press('s');
    if (await first.locator('[name="succeeded"]').isChecked()) await page.keyboard.press('s');
    await page.keyboard.press('3');
    check(await first.locator('[name="geometric_error"]').isChecked(), '3 toggles geometric error');
    await page.keyboard.press('n');
    await page.keyboard.type('gripper closed 2 cm short of the handle');
    await page.keyboard.press('Enter');
    await page.waitForSelector('#annotate-stages tr[data-stage]:nth-child(1).annotated', { timeout: 10000 });
    check((await rows.nth(0).locator('td.who').innerText()).startsWith('Ada Annotator'), 'the row names who saved it');
    check(await rows.nth(1).evaluate((tr) => tr.classList.contains('current')), 'Enter moved on to the next stage');
    // c: every other stage saved as shown (the automatic label confirmed).
    await page.keyboard.press('c');
    await page.waitForFunction((k) => document.querySelectorAll('#annotate-stages tr.annotated').length === k, n, { timeout: 20000 });
    check((await page.locator('#annotate-count').innerText()).startsWith(`${n} of ${n}`), 'all stages annotated');
    await shot(page, 'annotate-done');
    const saved = await page.evaluate(async (id) => (await fetch(`/api/episodes/${id}/stages`)).json(), episode);
    // ]: the next long-horizon episode of the batch, its panel fresh.
    let next = null;
    if (saved.next) {
      await Promise.all([page.waitForURL(`**/episodes/${saved.next}/review#annotate`, { timeout: 15000 }), page.keyboard.press(']')]);
      await page.waitForSelector('#annotate:not(.hidden) #annotate-stages tr[data-stage]', { timeout: 30000 });
      check(await page.inputValue('#annotator') === 'Ada Annotator', 'the name is remembered');
      next = saved.next;
      await shot(page, 'annotate-next-episode');
    }
    check(errors.length === 0, `no page errors: ${errors.join('; ')}`);
    say({ ok: true, stages: n, saved, next });
  } finally {
    await browser.close();
  }
}

main().catch((e) => { say({ ok: false, error: String(e && e.stack || e) }); process.exit(1); });
