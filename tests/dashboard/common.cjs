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

module.exports = { launch, say, shotter, check, text };
