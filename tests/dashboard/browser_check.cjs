// Drives Debian's chromium (headless, through playwright-core; no browser download) over the dashboard while a
// scripted agent runs episode EPISODE: the home page lists it live, the live page shows frames whose
// control-step label changes, calls and evaluator progress as they happen, the review page plays the video,
// steps with the keyboard, scrubs the timeline, opens a deep link and shows the observation the agent got, and
// the tasks page shows a rendered thumbnail and filters the pool. Prints JSON lines: {"event":"live-ready"} once the
// live page is connected (the test then starts the agent), finally {"ok":true,...}. Screenshots go to ARTIFACTS.
const { launch, say, shotter, check, text, login } = require('./common.cjs');

const [base, episode, artifacts, unimplemented] = process.argv.slice(2);
const shot = shotter(artifacts);

async function main() {
  const browser = await launch();
  const context = await browser.newContext({ viewport: { width: 1500, height: 1100 } });
  await login(context, base);
  const report = {};
  const errors = [];
  try {
    // Home: the prepared episode is listed; the list is pushed live.
    const home = await context.newPage();
    home.on('pageerror', (e) => errors.push(`home: ${e}`));
    await home.goto(`${base}/?task=T14`);
    await home.locator(`tr[data-id="${episode}"]`).waitFor({ timeout: 15000 });
    await home.locator('#live-status', { hasText: 'live' }).waitFor({ timeout: 10000 });

    // Live page, opened before the agent starts.
    const live = await context.newPage();
    live.on('pageerror', (e) => errors.push(`live: ${e}`));
    await live.goto(`${base}/episodes/${episode}`);
    await live.locator('#state', { hasText: 'live' }).waitFor({ timeout: 15000 });
    say({ event: 'live-ready' });

    await live.waitForFunction(() => Number(document.getElementById('frame-count').textContent) >= 3, null, { timeout: 120000 });
    const firstStep = await text(live, '#frame-step');
    const firstCount = Number(await text(live, '#frame-count'));
    await live.waitForFunction((s) => {
      const v = document.getElementById('frame-step').textContent;
      return v !== s && v !== 'settle' && v !== '–';
    }, firstStep, { timeout: 120000 });
    await live.locator('#calls li.ok', { hasText: 'osc_sequence' }).first().waitFor({ timeout: 120000 });
    await live.locator('#progress', { hasText: '/1' }).waitFor({ timeout: 60000 });
    const img = await live.locator('#frame').evaluate((e) => ({ w: e.naturalWidth, h: e.naturalHeight }));
    check(img.w === 512 && img.h === 256, `live frame is head|wrist 512x256, got ${JSON.stringify(img)}`);
    await shot(live, 'live-running');
    report.live = { firstStep, laterStep: await text(live, '#frame-step'), frames: Number(await text(live, '#frame-count')), firstCount };
    check(report.live.frames > firstCount, 'frames keep arriving');

    // A second viewer opened mid-episode catches up at once: calls so far and the newest frame.
    const late = await context.newPage();
    await late.goto(`${base}/episodes/${episode}`);
    await late.locator('#calls li.ok').first().waitFor({ timeout: 10000 });
    await late.waitForFunction(() => Number(document.getElementById('frame-count').textContent) >= 1, null, { timeout: 10000 });
    await late.close();

    // The end arrives live; the home list follows.
    await live.locator('#finished:not(.hidden)').waitFor({ timeout: 300000 });
    report.live.outcome = await text(live, '#outcome');
    report.live.calls = await live.locator('#calls li').count();
    report.live.errors = await live.locator('#calls li.error').count();
    check(report.live.errors >= 1, 'the rejected call shows as an error');
    report.live.stageItems = await live.locator('#stages li').count();
    await shot(live, 'live-finished');
    await home.locator(`tr[data-id="${episode}"] td.outcome:not(.RUNNING)`).waitFor({ timeout: 30000 });
    report.homeOutcome = await home.locator(`tr[data-id="${episode}"] td.outcome`).innerText();
    await shot(home, 'home');

    // Review: video, keyboard stepping, timeline scrub, deep link, the observation the agent received.
    const review = await context.newPage();
    review.on('pageerror', (e) => errors.push(`review: ${e}`));
    // The video is rendered from the state record after the episode: until it is there the page says how far
    // it is, and it puts the video in place by itself (no reload) once it is ready.
    await review.goto(`${base}/episodes/${episode}/review`);
    await review.waitForSelector('body[data-ready="true"]', { timeout: 30000 });
    if (await review.locator('#video-status').count()) {
      report.videoStatus = await text(review, '#video-status');
      check(/^video rendering, \d+ %/.test(report.videoStatus), `the rendering state: ${report.videoStatus}`);
      await shot(review, 'review-video-rendering');
    }
    await review.locator('video#video').waitFor({ state: 'attached', timeout: 600000 });
    const video = review.locator('video#video');
    check(await video.count(), 'the review page has the video');
    // Metadata first (duration); playing below needs the data, which a loaded machine may deliver slowly.
    const videoState = () => video.evaluate((v) => JSON.stringify({ readyState: v.readyState, networkState: v.networkState,
      error: v.error && v.error.message, currentTime: v.currentTime, paused: v.paused, buffered: v.buffered.length }));
    const waitVideo = async (fn, what) => {
      try { await review.waitForFunction(fn, null, { timeout: 60000 }); } catch (e) { throw new Error(`${what}: ${await videoState()}: ${e}`); }
    };
    await waitVideo(() => document.getElementById('video').readyState >= 1, 'video metadata');
    const duration = await video.evaluate((v) => v.duration);
    check(duration > 3, `video duration ${duration}`);
    await review.keyboard.press('Space');
    await waitVideo(() => document.getElementById('video').currentTime > 0.5, 'video plays on space');
    await review.keyboard.press('Space');
    check(await video.evaluate((v) => v.paused), 'space pauses');
    const before = await video.evaluate((v) => v.currentTime);
    const stepBefore = await text(review, '#cstep');
    await review.keyboard.press('ArrowRight');
    await review.keyboard.press('ArrowRight');
    await review.waitForTimeout(300);
    const after = await video.evaluate((v) => v.currentTime);
    check(Math.abs(after - before - 0.1) < 0.03, `two → steps move 0.1 s (${before} → ${after})`);
    check((await text(review, '#cstep')) !== stepBefore, 'the control-step label follows');
    const box = await review.locator('#timeline').boundingBox();
    await review.mouse.click(box.x + box.width * 0.8, box.y + box.height / 2);
    await review.waitForTimeout(300);
    const scrubbed = await video.evaluate((v) => v.currentTime);
    check(Math.abs(scrubbed - duration * 0.8) < 0.3, `timeline click seeks to 80% (${scrubbed} of ${duration})`);
    await review.locator('#observation img').first().waitFor({ timeout: 10000 });
    await review.waitForFunction(() => [...document.querySelectorAll('#observation img')].some((i) => i.naturalWidth > 0), null, { timeout: 10000 });
    check(/osc_sequence|finish_episode|start_episode/.test(await text(review, '#call-detail')), 'the call at this moment is shown');
    check((await text(review, '#result')).includes('private_evaluation'), 'the result record is shown');
    const stageRows = await review.locator('#stages tbody tr').count();
    const firstStage = await review.locator('#stages tbody tr td:nth-child(2)').first().innerText();
    check(stageRows >= 1 && /^1 · [A-Z]/.test(firstStage), `the per-stage diagnostics table is shown, names for people (${stageRows} rows: ${firstStage})`);
    check(/^01_/.test(await review.locator('#stages tbody tr td:nth-child(2)').first().getAttribute('title')), 'the record\'s stage name on hover');
    report.review = { duration, before, after, scrubbed, events: await review.locator('#events li').count() };
    await shot(review, 'review');
    await review.goto(`${base}/episodes/${episode}/review?t=1.5`);
    await review.waitForSelector('body[data-ready="true"]');
    await review.waitForFunction(() => Math.abs(document.getElementById('video').currentTime - 1.5) < 0.05, null, { timeout: 20000 });
    await shot(review, 'review-deeplink');

    // Tasks: the catalog with a rendered thumbnail for an implemented task, none for an unimplemented one.
    const tasks = await context.newPage();
    // This server renders nothing ahead (a fresh cache), so the page asks for every card's thumbnail at once; the
    // browser sends 6 at a time to one host and a 2-core machine renders one at a time, so T14's image waits behind
    // the cards above it (a few seconds each, minutes under load). Its render on request is checked first.
    const warm = await context.request.get(`${base}/tasks/T14/thumbnail.png`, { timeout: 120000 });
    check(warm.ok() && (warm.headers()['content-type'] || '').startsWith('image/png'), `T14's thumbnail renders on request (${warm.status()})`);
    await tasks.goto(`${base}/tasks`);
    const thumb = tasks.locator('#T14 img');
    await thumb.scrollIntoViewIfNeeded();
    await tasks.waitForFunction(() => document.querySelector('#T14 img').naturalWidth === 256, null, { timeout: 300000 });
    if (unimplemented === '-') {
      check((await tasks.locator('article.task.unimplemented').count()) === 0, 'every task is implemented and none is marked otherwise');
    } else {
      check((await tasks.locator(`#${unimplemented}`).innerText()).includes('not implemented'), `${unimplemented} shows as not implemented`);
    }
    await shot(tasks, 'tasks');
    // The pool: filter by suite and search by name through the page's own form; a stock entry renders its thumbnail.
    await tasks.fill('input[name="tasks"]', 'libero_90');
    await tasks.fill('input[name="q"]', 'microwave');
    await Promise.all([tasks.waitForNavigation(), tasks.click('form.task-filter button')]);
    const ids = await tasks.locator('article.pool-task').evaluateAll((a) => a.map((e) => e.dataset.id));
    check(ids.includes('libero_90/35') && ids.every((id) => id.startsWith('libero_90/')), `suite + search filter the pool (${ids.join(', ')})`);
    await tasks.waitForFunction(() => document.querySelector('article[data-id="libero_90/35"] img').naturalWidth === 256, null, { timeout: 120000 });
    check(/libero_90\/35/.test(await tasks.locator('article[data-id="libero_90/35"] a.teleop-link').getAttribute('href')), 'a stock entry links to teleop');
    // The pool pages below are checked by their text: they do not wait for the thumbnails, which render one at a
    // time behind those the pages before asked for.
    await tasks.goto(`${base}/tasks?tasks=robomemarena&group=long_horizon`, { waitUntil: 'domcontentloaded' });
    const t23 = await tasks.locator('article[data-id="robomemarena/4"]').innerText();
    check(t23.includes('runs as T23'), 'a release-backed entry says what it runs as');
    report.pool = { microwave: ids, summary: await text(tasks, '#task-summary') };
    await shot(tasks, 'tasks-pool');
    // Any task selection, the same syntax as the commands': a release task and pool entries (by id and by name), in
    // one page; only tasks whose thumbnails the pages above asked for, so no new renders queue ahead of the next page.
    await tasks.goto(`${base}/tasks?tasks=${encodeURIComponent('T14,libero_90/35,robomemarena/robomemarena_task_04')}`, { waitUntil: 'domcontentloaded' });
    const mixed = await tasks.locator('article.task').evaluateAll((a) => a.map((e) => e.id || e.dataset.id));
    check(mixed.join(',') === 'T14,libero_90/35,robomemarena/4', `a selection mixes release tasks and entries in its order (${mixed.join(', ')})`);
    check((await tasks.locator('input[name="tasks"]').inputValue()) === 'T14,libero_90/35,robomemarena/robomemarena_task_04', 'the field shows the selection');
    await shot(tasks, 'tasks-selection');
    await tasks.goto(`${base}/tasks?tasks=T14,kitchen`, { waitUntil: 'domcontentloaded' });
    check((await tasks.locator('#task-selection-error').innerText()).includes('no pool suite "kitchen"'), 'a selection with a typo says what is accepted');
    await tasks.goto(`${base}/tasks?suite=vlabench_perception`, { waitUntil: 'domcontentloaded' });
    check((await tasks.locator('article[data-id="vlabench_perception/1"]').innerText()).includes('does not run here'), 'an excluded entry says so');
    check(errors.length === 0, `no page errors: ${errors.join('; ')}`);
    say({ ok: true, ...report });
  } finally {
    await browser.close();
  }
}

main().catch((e) => { say({ ok: false, error: String(e && e.stack || e) }); process.exit(1); });
