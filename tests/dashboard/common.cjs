// Shared by the dashboard's browser scripts: Debian's chromium through playwright-core (no browser download) and
// the small assertion and output helpers every script uses.
const { chromium } = require('playwright-core');
const path = require('path');

const executablePath = process.env.LIBERO_AGENT_CHROMIUM || '/usr/bin/chromium';

/** Headless chromium that may autoplay video (the review and demo pages play MP4s without a click). */
function launch() {
  return chromium.launch({ executablePath, headless: true, args: ['--no-sandbox', '--autoplay-policy=no-user-gesture-required'] });
}

const say = (o) => process.stdout.write(JSON.stringify(o) + '\n');
const shotter = (artifacts) => (page, name) => page.screenshot({ path: path.join(artifacts, `${name}.png`), fullPage: true });
function check(cond, what) { if (!cond) throw new Error(`check failed: ${what}`); }
const text = (page, sel) => page.locator(sel).innerText();

/**
 * Opens an operator session in `context` the way a person does: the one-time login link `serve` prints
 * (`/?token=…`), which sets the session cookie and redirects to the page without the token.
 */
async function login(context, base) {
  const token = process.env.LIBERO_OPERATOR_TOKEN;
  check(token, 'LIBERO_OPERATOR_TOKEN is set');
  const page = await context.newPage();
  await page.goto(`${base}/?token=${encodeURIComponent(token)}`);
  check(!page.url().includes('token='), `the login link redirects to a URL without the token (${page.url()})`);
  const cookies = await context.cookies();
  check(cookies.some((c) => c.name === 'libero_session' && c.httpOnly && c.value !== token), 'an HttpOnly session cookie that is not the token');
  await page.close();
}

/**
 * Runs `body(context, report, errors)` in a logged-in 1500×1100 chromium context, then prints `report` as one JSON line
 * (`ok`, or the error and the page errors `body` collected) and exits 0 or 1.
 */
async function runChecks(base, body) {
  const browser = await launch();
  const report = {};
  const errors = [];
  try {
    const context = await browser.newContext({ viewport: { width: 1500, height: 1100 } });
    await login(context, base);
    await body(context, report, errors);
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

module.exports = { launch, login, say, shotter, check, text, runChecks };
