// Opens an episode's review page in Debian's chromium (headless, playwright-core) and checks the agent's transcript
// beside the robot's calls: the whole transcript lists the agent's printed lines, and picking one of them selects
// the call it led to, whose panel then shows what the agent printed between the previous call and it.
// Usage: node agent_review_check.cjs BASE EPISODE ARTIFACTS. Prints one JSON line, {"ok":true,...} or
// {"ok":false,"error":...}. Screenshots go to ARTIFACTS.
const { launch, say, shotter, check, login, text } = require('./common.cjs');

const [base, episode, artifacts] = process.argv.slice(2);
const shot = shotter(artifacts);

async function main() {
  const browser = await launch();
  const errors = [];
  try {
    const context = await browser.newContext({ viewport: { width: 1500, height: 1200 } });
    await login(context, base);
    const page = await context.newPage();
    page.on('pageerror', (e) => errors.push(`${page.url()}: ${e}`));
    await page.goto(`${base}/episodes/${episode}/review`);
    await page.waitForSelector('body[data-ready="true"]', { timeout: 60000 });
    const count = Number(await page.evaluate(() => document.body.dataset.agentEvents));
    check(count >= 8, `the transcript loaded (${count} events)`);
    const log = await text(page, '#agent-log');
    for (const n of [1, 2, 3, 4, 5, 8]) check(log.includes(`agent line ${n}`), `the transcript lists line ${n}: ${log.slice(0, 500)}`);
    check(log.includes('my key is <redacted>'), 'the key the agent printed is scrubbed');
    await page.locator('#agent-log li', { hasText: 'agent line 4' }).first().click();
    await page.waitForFunction(() => document.getElementById('agent-before').innerText.includes('agent line 4'), null, { timeout: 15000 });
    const before = await text(page, '#agent-before');
    check(before.includes('agent line 3') && !before.includes('agent line 2') && !before.includes('agent line 5'), `only what came before the call: ${before}`);
    check((await text(page, '#call-detail')).includes('osc_sequence'), 'the call it led to is selected');
    await shot(page, 'agent-transcript-review');
    check(errors.length === 0, `no page errors: ${errors.join('; ')}`);
    say({ ok: true, events: count });
  } finally {
    await browser.close();
  }
}

main().catch((e) => { say({ ok: false, error: String(e && e.stack || e) }); process.exit(1); });
