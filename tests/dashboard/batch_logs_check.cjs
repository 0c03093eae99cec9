// A batch's rollouts in Debian's chromium (headless, playwright-core): the Results page of one batch lists every
// rollout with its review and its logs; following "logs" opens the rollout's page, which shows the agent's stdout and
// stderr, the harness manifest and the transcript the runner kept (checked by content), says which files were not
// written and refuses the one the test replaced with a symlink; its plain-text link serves the same stdout; the
// review link opens the episode's review, which names the batch, and the batch link leads back.
// Usage: node batch_logs_check.cjs BASE BATCH ROLLOUT EPISODE STDERR_MARKER REFUSED_FILE ARTIFACTS. Prints one JSON line.
const { launch, say, shotter, check, login } = require('./common.cjs');

const [base, batch, rollout, episode, marker, refused, artifacts] = process.argv.slice(2);
const shot = shotter(artifacts);

async function main() {
  const browser = await launch();
  const errors = [];
  const out = { ok: true };
  try {
    const context = await browser.newContext({ viewport: { width: 1400, height: 1000 } });
    await login(context, base);
    const page = await context.newPage();
    page.on('pageerror', (e) => errors.push(`${page.url()}: ${e}`));

    await page.goto(`${base}/results?batch=${batch}`);
    const row = page.locator(`#rollouts tr[data-rollout="${rollout}"]`);
    check(await row.count() === 1, `the Rollouts table lists ${rollout}`);
    out.rollout_rows = await page.locator('#rollouts tbody tr').count();
    check(await row.locator('a.review-link').getAttribute('href') === `/episodes/${episode}/review`, 'the row links to the episode review');
    check(await page.locator(`#per-task a.logs-link[href="/results/logs/${batch}/${rollout}"]`).count() === 1, 'the per-task cell links to the logs too');
    await page.locator('#rollouts').screenshot({ path: require('path').join(artifacts, 'results-rollouts.png') });

    await Promise.all([page.waitForURL(`**/results/logs/${batch}/${rollout}`, { timeout: 15000 }), row.locator('a.logs-link').click()]);
    const textOf = (slug) => page.locator(`#log-${slug}-text`).innerText();
    const stdout = await textOf('stdout');
    check(stdout.includes('"agent":"libero-agent-reference"'), `the agent's stdout is shown: ${stdout.slice(0, 200)}`);
    check((await textOf('stderr')).includes(marker), `the agent's stderr shows ${marker}`);
    const manifest = await textOf('harness_manifest');
    check(manifest.includes('libero.multi_agent_harness_run.v1') && manifest.includes(`"rollout_id": "${rollout}"`), 'the harness manifest is shown');
    check(manifest.includes(`"episode_id": "${episode}"`), 'the manifest names the episode');
    const transcript = await textOf('transcript');
    check(transcript.includes('"kind":"message"') && transcript.includes('libero-agent-reference'), `the transcript is shown: ${transcript.slice(0, 200)}`);
    if (refused !== 'harness_usage') check((await textOf('harness_usage')).includes('"source"'), 'the token usage is shown');
    const gateway = await page.locator('#log-files tr[data-file="model_api"]').innerText();
    check(/not written/.test(gateway), `no gateway records without the sandbox: ${gateway}`);
    if (refused) {
      const r = await page.locator(`#log-files tr[data-file="${refused}"]`).innerText();
      check(/refused/.test(r) && await page.locator(`#log-${refused}-text`).count() === 0, `the symlinked ${refused} is refused: ${r}`);
      out.refused = r.trim();
    }
    check((await page.locator('#batch-link').getAttribute('href')) === `/results?batch=${batch}`, 'the page links to its batch');
    await shot(page, 'rollout-logs');

    // the plain text of the stdout: the same bytes as shown
    const raw = page.locator('#log-files tr[data-file="stdout"] a.raw-link');
    await Promise.all([page.waitForURL(`**/results/logs/${batch}/${rollout}/stdout`, { timeout: 15000 }), raw.click()]);
    const plain = await page.locator('body').innerText();
    check(plain.trim() === stdout.trim(), 'the plain-text stdout is what the page shows');
    await page.goBack();

    await Promise.all([page.waitForURL(`**/episodes/${episode}/review`, { timeout: 15000 }), page.locator('#review-link').click()]);
    await page.waitForSelector('body[data-ready="true"]', { timeout: 30000 });
    check((await page.locator('#batch-link').innerText()).trim() === batch, 'the review names its batch');
    await Promise.all([page.waitForURL(`**/results?batch=${batch}`, { timeout: 15000 }), page.locator('#batch-link').click()]);
    check(await page.locator(`#rollouts tr[data-rollout="${rollout}"]`).count() === 1, 'back on the batch');

    check(errors.length === 0, `no page errors: ${errors.join('; ')}`);
    say(out);
  } finally {
    await browser.close();
  }
}

main().catch((e) => { say({ ok: false, error: String(e && e.stack || e) }); process.exit(1); });
