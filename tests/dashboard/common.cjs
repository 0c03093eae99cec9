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

module.exports = { launch, login, say, shotter, check, text };
