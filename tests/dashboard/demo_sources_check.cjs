// A demonstration links to its source episode's review when this server's store knows the episode, in Debian's
// chromium (headless, playwright-core): on the Demonstrations page and on the task's page, the bundle recorded from
// an episode of this server links to `/episodes/<id>/review` (followed: the review opens), and the bundle recorded
// from an episode of another data directory shows its id without a link.
// Usage: node demo_sources_check.cjs BASE TASK KNOWN_EPISODE UNKNOWN_EPISODE ARTIFACTS. Prints one JSON line.
const { launch, say, shotter, check, login } = require('./common.cjs');

const [base, task, known, unknown, artifacts] = process.argv.slice(2);
const shot = shotter(artifacts);

async function main() {
  const browser = await launch();
  const errors = [];
  const out = { ok: true };
  try {
    const context = await browser.newContext({ viewport: { width: 1400, height: 900 } });
    await login(context, base);
    const page = await context.newPage();
    page.on('pageerror', (e) => errors.push(`${page.url()}: ${e}`));

    await page.goto(`${base}/demos`);
    const knownRow = page.locator(`#bundles tr[data-key="${task}/${known}"]`);
    const unknownRow = page.locator(`#bundles tr[data-key="${task}/${unknown}"]`);
    await knownRow.locator('a.source-episode').waitFor({ timeout: 15000 });
    check(await knownRow.locator('a.source-episode').getAttribute('href') === `/episodes/${known}/review`, 'the known source links to its review');
    check(await unknownRow.count() === 1, 'the other bundle is listed');
    check(await unknownRow.locator('a.source-episode').count() === 0, 'an episode the store does not know is not linked');
    check((await unknownRow.locator('small.source-episode').innerText()).trim() === unknown, 'its id is shown');
    await shot(page, 'demos-sources');
    await Promise.all([page.waitForURL(`**/episodes/${known}/review`, { timeout: 15000 }), knownRow.locator('a.source-episode').click()]);
    await page.waitForSelector('body[data-ready="true"]', { timeout: 30000 });

    await page.goto(`${base}/tasks/${task}`);
    const onTask = page.locator(`#task-demos tr[data-key="${task}/${known}"] a.source-episode`);
    check(await onTask.getAttribute('href') === `/episodes/${known}/review`, 'the task page links the known source');
    check(await page.locator(`#task-demos tr[data-key="${task}/${unknown}"] a.source-episode`).count() === 0, 'and not the other');
    out.task_page_unknown = (await page.locator(`#task-demos tr[data-key="${task}/${unknown}"] td:nth-child(2)`).innerText()).trim();
    await page.locator('#task-demos').screenshot({ path: require('path').join(artifacts, 'task-demo-sources.png') });
    await Promise.all([page.waitForURL(`**/episodes/${known}/review`, { timeout: 15000 }), onTask.click()]);

    check(errors.length === 0, `no page errors: ${errors.join('; ')}`);
    say(out);
  } finally {
    await browser.close();
  }
}

main().catch((e) => { say({ ok: false, error: String(e && e.stack || e) }); process.exit(1); });
