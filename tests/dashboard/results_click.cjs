// Opens the Results page in Debian's chromium (headless, playwright-core), checks the main table and the per-task
// table and the task-pool tables, clicks the first rollout link of task TASK and expects that episode's review page to load with its
// result record. Usage: node results_click.cjs BASE TASK ARTIFACTS. Prints one JSON line, {"ok":true,...} or
// {"ok":false,"error":...}. Screenshots go to ARTIFACTS.
const { launch, say, shotter, check, login } = require('./common.cjs');

const [base, task, artifacts] = process.argv.slice(2);
const shot = shotter(artifacts);

async function main() {
  const browser = await launch();
  const errors = [];
  try {
    const context = await browser.newContext({ viewport: { width: 1500, height: 1000 } });
    await login(context, base);
    const page = await context.newPage();
    page.on('pageerror', (e) => errors.push(`${page.url()}: ${e}`));
    await page.goto(`${base}/results`);
    check(await page.locator('#main-table tbody tr').count() > 0, 'the main table has rows');
    const row = page.locator('#per-task tbody tr', { has: page.locator('td', { hasText: new RegExp(`^${task}$`) }) });
    const link = row.locator('a.outcome').first();
    await link.waitFor({ timeout: 10000 });
    const href = await link.getAttribute('href');
    check(/^\/episodes\/[^/]+\/review$/.test(href), `a review link, got ${href}`);
    await shot(page, 'results');
    // tokens with their source on every main-table row, and the toolbox each batch ran with
    const tokenCells = await page.locator('#main-table td.tokens').allTextContents();
    check(tokenCells.length > 0 && tokenCells.every((t) => /\(.+\)/.test(t)), `every main-table row names its token source: ${tokenCells}`);
    check(await page.locator('#toolboxes tbody tr').count() > 0, 'the toolbox table has a row per batch');
    await page.locator('#toolboxes').screenshot({ path: require('path').join(artifacts, 'results-toolbox.png') });
    await page.locator('#main-table').screenshot({ path: require('path').join(artifacts, 'results-main-tokens.png') });
    // the pool batch's per-suite table and per-task rows, beside the paper's table
    check(await page.locator('#pool-suites tbody tr').count() >= 2, 'the task-pool table has a row per suite');
    check(await page.locator('#pool-tasks a.outcome').count() >= 4, 'every pool rollout links to its review');
    await page.locator('#pool-suites').screenshot({ path: require('path').join(artifacts, 'results-pool.png') });
    await Promise.all([page.waitForURL(`**${href}`, { timeout: 15000 }), link.click()]);
    await page.waitForSelector('body[data-ready="true"]', { timeout: 30000 });
    await page.waitForFunction(() => (document.getElementById('result') || {}).textContent?.includes('private_evaluation'), null, { timeout: 15000 });
    await shot(page, 'results-review');
    check(errors.length === 0, `no page errors: ${errors.join('; ')}`);
    say({ ok: true, review: href });
  } finally {
    await browser.close();
  }
}

main().catch((e) => { say({ ok: false, error: String(e && e.stack || e) }); process.exit(1); });
