// The browser's own teleop latency, beside `libero-agent bench teleop`: drives /teleop/TASK in Debian's chromium
// (headless, playwright-core) and, for each of PRESSES key presses (`w` and `s` by turns, each held until its
// effect is on screen), measures from the page's keydown event to the paint of the first frame that shows the
// action carrying that key (the page's own latency label names that frame: it is set when the frame whose control
// step reaches that action arrives, right after the image is handed the frame). "Painted" is the image decoded and
// the next animation frame's paint done (a requestAnimationFrame callback, then a task after it). Also reports the
// page's own label (keydown to the frame's arrival in JavaScript) for the same presses.
// Usage: node teleop_latency.cjs BASE TASK [PRESSES]. Prints one JSON line {"ok":true, "key_to_paint_ms":{p50,…}}.
const { launch, say, check, login } = require('./common.cjs');

const [base, task, pressesArg] = process.argv.slice(2);
const presses = Number(pressesArg || 30);
/** Presses measured but not counted: the first frames of a fresh episode and a cold page. */
const WARMUP = 3;

const percentile = (xs, p) => {
  const v = [...xs].sort((a, b) => a - b);
  return v.length ? v[Math.min(v.length - 1, Math.ceil((p / 100) * v.length) - 1)] : null;
};
const summary = (xs) => ({ p50: percentile(xs, 50), p95: percentile(xs, 95), min: Math.min(...xs), max: Math.max(...xs), n: xs.length });

/** Installed in the page: records each keydown's time, and for the newest one the paint of the frame the page's
 * latency label is next set for. */
function instrument() {
  const w = window;
  w.__lat = { key: null, results: [] };
  document.addEventListener('keydown', (e) => {
    if (!e.repeat) w.__lat.key = { t: performance.now(), done: false };
  }, true);
  const img = document.getElementById('frame');
  new MutationObserver(() => {
    const k = w.__lat.key;
    if (!k || k.done) return;
    k.done = true;
    const arrived = performance.now();
    const label = document.getElementById('latency').textContent;
    const painted = () => requestAnimationFrame(() => setTimeout(() => {
      w.__lat.results.push({ paint: performance.now() - k.t, arrival: arrived - k.t, label });
    }, 0));
    // the label changes in the same task that set the image's new src: wait for that image to decode
    img.decode().then(painted, painted);
  }).observe(document.getElementById('latency'), { childList: true, characterData: true, subtree: true });
}

async function main() {
  const browser = await launch();
  const context = await browser.newContext({ viewport: { width: 1400, height: 1000 } });
  await login(context, base);
  const report = { task, presses };
  try {
    const page = await context.newPage();
    await page.goto(`${base}/teleop/${task}`);
    await page.waitForFunction(() => document.getElementById('frame') && document.getElementById('latency'));
    await page.evaluate(instrument);
    await page.locator('.teleop').focus();
    // A page that creates its episode on the first action gets one here; either way, frames must flow.
    const flowing = () => page.waitForFunction(() => Number(document.getElementById('frame-count').textContent) >= 2, null, { timeout: 180000 });
    await flowing().catch(async () => { await page.keyboard.press('w'); await flowing(); });
    const paint = [];
    const arrival = [];
    for (let i = 0; i < presses + WARMUP; i++) {
      const key = i % 2 === 0 ? 'w' : 's';
      const before = await page.evaluate(() => window.__lat.results.length);
      await page.keyboard.down(key);
      await page.waitForFunction((n) => window.__lat.results.length > n, before, { timeout: 30000 });
      await page.keyboard.up(key);
      const r = await page.evaluate(() => window.__lat.results[window.__lat.results.length - 1]);
      if (i >= WARMUP) {
        paint.push(r.paint);
        arrival.push(r.arrival);
      }
      await page.waitForTimeout(150 + Math.random() * 100); // presses at no fixed phase to the 100 ms batches
    }
    report.key_to_paint_ms = summary(paint);
    report.key_to_frame_arrival_ms = summary(arrival);
    report.frames = Number(await page.locator('#frame-count').innerText());
    check(paint.length === presses, `${paint.length} presses measured`);
    report.ok = true;
  } catch (e) {
    report.ok = false;
    report.error = String(e && e.stack ? e.stack : e);
  } finally {
    await browser.close();
  }
  say(report);
  process.exit(report.ok ? 0 : 1);
}

main();
