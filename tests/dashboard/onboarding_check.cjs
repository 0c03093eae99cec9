// A fresh server's console as a newcomer meets it: the home page says what to do next (expert, agent, batch,
// teleop), the prepare button yields an MCP configuration to copy, and the commands name this very server.
const { launch, login, say, shotter, check, text } = require('./common.cjs');

const [base, artifacts] = process.argv.slice(2);
const shot = shotter(artifacts);

(async () => {
  const browser = await launch();
  const context = await browser.newContext({ viewport: { width: 1400, height: 1000 } });
  await login(context, base);
  try {
    const page = await context.newPage();
    await page.goto(`${base}/`);
    const guide = page.locator('#getting-started');
    check(await guide.evaluate((d) => d.open), 'the getting-started panel is open on an empty console');
    const guideText = await text(page, '#getting-started');
    for (const words of ['expert --task T14', `--server ${base}`, 'run --experiment main_table', 'Prepare a T14 episode']) {
      check(guideText.includes(words), `the guide mentions "${words}"`);
    }
    check((await page.locator('#teleop-link').getAttribute('href')) === '/teleop/T14', 'a teleop link');
    await shot(page, 'onboarding-empty');
    await page.click('#prepare-episode');
    await page.waitForSelector('#prepared:not([hidden])', { timeout: 120000 });
    const config = JSON.parse(await text(page, '#mcp-config'));
    const server = config.mcpServers.libero;
    check(server.url.startsWith(`${base}/mcp/ep-`), `the MCP URL points at this server (${server.url})`);
    check(/^Bearer [0-9a-f]{64}$/.test(server.headers.Authorization), 'a bearer header');
    const reference = await text(page, '#reference-agent');
    check(reference.includes(' agent --workspace '), `the reference-agent command (${reference})`);
    await page.waitForSelector('#episodes tr', { timeout: 30000 });
    // the table says when each episode started, in minutes UTC, the record's timestamp on hover
    const started = page.locator('#episodes tr').first().locator('td time');
    check(/^\d{4}-\d{2}-\d{2} \d{2}:\d{2} UTC$/.test(await started.innerText()), `a start time (${await started.innerText()})`);
    check(/^\d{4}-\d{2}-\d{2}T/.test(await started.getAttribute('title')), 'the record\'s timestamp on hover');
    await shot(page, 'onboarding-prepared');
    say({ ok: true, mcp_url: server.url });
  } catch (err) {
    say({ ok: false, error: String(err) });
    process.exitCode = 1;
  } finally {
    await browser.close();
  }
})();
