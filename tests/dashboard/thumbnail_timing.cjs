// Measures how a page of task thumbnails appears in Debian's chromium (headless, playwright-core), for the numbers in
// docs/console.md ("Thumbnails on demand"): first contentful paint, DOMContentLoaded and the load event of the page,
// then when the first thumbnail in the window and every thumbnail in the window (1280 × 1000) show a picture.
// Not a test (nothing is asserted about time): run it against a server on a fresh data directory.
// Usage: node thumbnail_timing.cjs BASE PATH [TIMEOUT_S] [SHOT_PREFIX]. Prints one JSON line; with SHOT_PREFIX, a
// screenshot right after DOMContentLoaded (`PREFIX-first.png`) and one at the end (`PREFIX-end.png`).
const { launch, say, login } = require('./common.cjs');

const [base, path, timeoutS = '400', shots] = process.argv.slice(2);

async function main() {
  const browser = await launch();
  try {
    const context = await browser.newContext({ viewport: { width: 1280, height: 1000 } });
    await login(context, base);
    const page = await context.newPage();
    const t0 = Date.now();
    let load = null;
    page.on('load', () => { load = Date.now() - t0; });
    await page.goto(`${base}${path}`, { waitUntil: 'commit' });
    await page.waitForLoadState('domcontentloaded');
    const dcl = Date.now() - t0;
    if (shots) await page.screenshot({ path: `${shots}-first.png` });
    // every thumbnail image whose box is in the window, and how many of them show a picture
    const inView = () => page.evaluate(() => {
      const imgs = [...document.querySelectorAll('img')].filter((i) => /thumbnail/.test(i.dataset.thumb || i.src || ''));
      const seen = imgs.filter((i) => { const r = i.getBoundingClientRect(); return r.bottom > 0 && r.top < window.innerHeight; });
      return { total: imgs.length, in_view: seen.length, shown: seen.filter((i) => i.complete && i.naturalWidth > 0).length };
    });
    let first = null;
    let all = null;
    let last = null;
    const deadline = Date.now() + Number(timeoutS) * 1000;
    while (Date.now() < deadline) {
      last = await inView();
      if (first === null && last.shown > 0) first = Date.now() - t0;
      if (last.in_view > 0 && last.shown === last.in_view) { all = Date.now() - t0; break; }
      await page.waitForTimeout(100);
    }
    if (shots) await page.screenshot({ path: `${shots}-end.png` });
    const fcp = await page.evaluate(() => (performance.getEntriesByName('first-contentful-paint')[0] || {}).startTime ?? null);
    say({ ok: true, path, fcp_ms: fcp && Math.round(fcp), dom_content_loaded_ms: dcl, load_ms: load, first_thumbnail_ms: first,
      all_in_view_ms: all, thumbnails: last });
  } finally {
    await browser.close();
  }
}

main().catch((e) => { say({ ok: false, error: String(e && e.stack || e) }); process.exit(1); });
