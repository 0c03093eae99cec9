// The console where people stumble: the login page of a loopback server (what it says about where the server
// listens and where the token is), an unknown address and an unknown episode's review (pages with the console's
// navigation and a plain message, not JSON), and the favicon.
const { launch, login, say, shotter, check, text } = require('./common.cjs');

const [base, artifacts, tokenFile] = process.argv.slice(2);
const shot = shotter(artifacts);

(async () => {
  const browser = await launch();
  try {
    // Not signed in: any page leads to the login form.
    const fresh = await browser.newContext({ viewport: { width: 1200, height: 700 } });
    const page = await fresh.newPage();
    await page.goto(`${base}/tasks`);
    check(new URL(page.url()).pathname === '/login', `an unsigned visit lands on the login form (${page.url()})`);
    const loginText = await text(page, 'main');
    check(loginText.includes(tokenFile), `the login page names the token file ${tokenFile}`);
    check(!loginText.includes('beyond loopback'), 'a loopback server does not claim to listen beyond loopback');
    check((await text(page, '#listen')).includes('127.0.0.1:'), 'the login page says where the server listens');
    const icon = await page.evaluate(async () => { const r = await fetch('/favicon.ico'); return { status: r.status, type: r.headers.get('content-type'), size: (await r.arrayBuffer()).byteLength }; });
    check(icon.status === 200 && icon.type === 'image/x-icon' && icon.size > 100, `the favicon is served (${JSON.stringify(icon)})`);
    await shot(page, 'console-login');
    await fresh.close();

    const context = await browser.newContext({ viewport: { width: 1200, height: 700 } });
    await login(context, base);
    const p = await context.newPage();
    const missing = await p.goto(`${base}/no/such/page`);
    check(missing.status() === 404, `an unknown address answers 404 (${missing.status()})`);
    check((await text(p, '#error-title')).startsWith('404'), 'the page says 404');
    check(await p.locator('header.top nav a[href="/tasks"]').count() === 1, 'the error page carries the navigation');
    await shot(p, 'console-error-404');
    const review = await p.goto(`${base}/episodes/ep-20990101T000000Z-none/review`);
    check(review.status() === 404, `an unknown episode's review answers 404 (${review.status()})`);
    const message = await text(p, '#error-message');
    check(message.includes('ep-20990101T000000Z-none'), `the message names the episode (${message})`);
    await shot(p, 'console-error-episode');
    await p.click('header.top nav a[href="/tasks"]');
    await p.waitForURL(`${base}/tasks`);
    check(await p.locator('h1').count() > 0, 'the navigation of an error page leads on to the tasks page');
    say({ ok: true, message });
  } catch (err) {
    say({ ok: false, error: String(err) });
    process.exitCode = 1;
  } finally {
    await browser.close();
  }
})();
