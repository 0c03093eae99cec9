// The task pages in Debian's chromium (headless, playwright-core): task cards fit their width at 1280 and 1920 px
// (release tasks and libero_90, whose names are long), a card links to its task page, the pages of T14 and of a
// pool entry show the instruction, K, stage names, both camera images (loaded), teleop and back links, the given
// episode and its batch cell; the review page links to the task page and its Stages table fits at 1400 px; the
// Results page links the task to its page; the warm Tasks page loads with its images in under 2 s.
// Usage: node task_pages_check.cjs BASE EPISODE_ID POOL_TASK POOL_INSTRUCTION ARTIFACTS. Prints one JSON line.
const path = require('path');
const { launch, say, shotter, check, login } = require('./common.cjs');

const [base, episode, poolTask, poolInstruction, artifacts] = process.argv.slice(2);
const shot = shotter(artifacts);

/** Cards wider than their box, and whether the document is wider than the window. */
async function overflow(page) {
  return page.evaluate(() => {
    const cards = [...document.querySelectorAll('.task')];
    const bad = cards.filter((c) => c.scrollWidth > c.clientWidth).map((c) => c.id || c.dataset.id);
    const doc = document.documentElement;
    return { cards: cards.length, bad, docWidth: doc.scrollWidth, viewport: window.innerWidth };
  });
}

/** Every image on the page has loaded (naturalWidth > 0). */
async function imagesLoaded(page, selector) {
  await page.waitForFunction((sel) => [...document.querySelectorAll(sel)].every((i) => i.complete && i.naturalWidth > 0), selector, { timeout: 120000 });
  return page.evaluate((sel) => [...document.querySelectorAll(sel)].map((i) => i.naturalWidth), selector);
}

async function taskPage(page, url, name, want) {
  await page.goto(url);
  const text = await page.locator('main').innerText();
  check((await page.locator('#instruction').innerText()).includes(want.instruction), `${url}: the instruction "${want.instruction}"`);
  check((await page.locator('#task-k').innerText()).trim() === String(want.k), `${url}: K = ${want.k}`);
  check(await page.locator('#task-stages tbody tr').count() >= 1, `${url}: the stage list`);
  for (const s of want.stages || []) check(text.includes(s), `${url}: stage ${s}`);
  const widths = await imagesLoaded(page, '#head-view, #wrist-view');
  check(widths.length === 2 && widths.every((w) => w > 0), `${url}: both camera images load (${widths})`);
  const teleop = await page.locator('#teleop-link').getAttribute('href');
  check(teleop === want.teleop, `${url}: teleop link ${teleop}`);
  const back = await page.locator('#back-to-tasks').getAttribute('href');
  check(back.startsWith('/tasks'), `${url}: a link back to the Tasks page (${back})`);
  check(!/latch_joint|"min"|threshold|pose/i.test(await page.locator('#judged').innerText()), `${url}: the checker text has no private parameter`);
  await shot(page, name);
  return text;
}

async function main() {
  const browser = await launch();
  const errors = [];
  const out = { ok: true };
  try {
    for (const width of [1280, 1920]) {
      const context = await browser.newContext({ viewport: { width, height: 1000 } });
      await login(context, base);
      const page = await context.newPage();
      page.on('pageerror', (e) => errors.push(`${page.url()}: ${e}`));
      // Layout does not wait on images (each has its size): thumbnails not rendered yet are not asked for here.
      await page.route(/thumbnail\.png/, (r) => r.abort());
      for (const [suite, label] of [['', 'release'], ['libero_90', 'libero_90']]) {
        await page.goto(`${base}/tasks${suite ? `?suite=${suite}` : ''}`);
        const o = await overflow(page);
        check(o.cards > 5, `${label} at ${width}: cards shown (${o.cards})`);
        check(o.bad.length === 0, `${label} at ${width}: cards wider than their box: ${o.bad.join(', ')}`);
        check(o.docWidth <= o.viewport, `${label} at ${width}: the page is ${o.docWidth} px wide in a ${o.viewport} px window`);
        out[`${label}_${width}`] = o;
        await page.screenshot({ path: path.join(artifacts, `tasks-${label}-${width}.png`) });
      }
      await context.close();
    }

    const context = await browser.newContext({ viewport: { width: 1400, height: 1000 } });
    await login(context, base);
    const page = await context.newPage();
    page.on('pageerror', (e) => errors.push(`${page.url()}: ${e}`));

    // The warm Tasks page (its thumbnails cached): the page and every image in under 2 s.
    const t0 = Date.now();
    await page.goto(`${base}/tasks?q=T14`, { waitUntil: 'load' });
    await imagesLoaded(page, '.task img');
    out.warm_tasks_page_ms = Date.now() - t0;
    check(out.warm_tasks_page_ms < 2000, `the warm Tasks page took ${out.warm_tasks_page_ms} ms`);

    // A card links to its task page.
    await Promise.all([page.waitForURL('**/tasks/T14', { timeout: 15000 }), page.locator('#T14 a.task-page-link').click()]);
    const t14 = await taskPage(page, `${base}/tasks/T14`, 'task-T14', {
      instruction: 'close the top drawer of the cabinet', k: 1, teleop: '/teleop/T14',
    });
    check(t14.includes(episode), `the T14 page lists episode ${episode}`);
    const epLink = await page.locator(`#task-episodes tr[data-episode="${episode}"] a`).getAttribute('href');
    check(epLink === `/episodes/${episode}/review`, `the episode links to its review (${epLink})`);
    check(await page.locator('#task-batches a.outcome').count() >= 1, 'the T14 page shows its batch cell with a rollout link');

    await taskPage(page, `${base}/tasks/${poolTask}`, 'task-pool', { instruction: poolInstruction, k: 1, teleop: `/teleop/${poolTask}` });
    const back = await page.locator('#back-to-tasks').getAttribute('href');
    // the pool suite's other cards are not rendered in this test: their thumbnails are not asked for
    await page.route(/thumbnail\.png/, (r) => r.abort());
    await page.goto(`${base}${back}`);
    check(await page.locator(`article[data-id="${poolTask}"] a.task-page-link`).count() === 1, 'the pool card links to its page');

    // The review page shows the instruction and links to the task page; its Stages table fits at 1400 px.
    await page.goto(`${base}/episodes/${episode}/review`);
    await page.waitForSelector('body[data-ready="true"]', { timeout: 30000 });
    await page.waitForFunction(() => document.querySelectorAll('#stages th').length > 0, null, { timeout: 15000 });
    check((await page.locator('#task-page-link').getAttribute('href')) === '/tasks/T14', 'the review links to /tasks/T14');
    check((await page.locator('#task-instruction').innerText()).includes('close the top drawer'), 'the review shows the instruction');
    const fit = await page.evaluate(() => {
      const t = document.getElementById('stages').getBoundingClientRect();
      return { right: t.right, viewport: window.innerWidth, doc: document.documentElement.scrollWidth };
    });
    check(fit.right <= fit.viewport && fit.doc <= fit.viewport, `the Stages table fits at 1400 px: ${JSON.stringify(fit)}`);
    out.review_stages = fit;
    await shot(page, 'review-1400');

    // The Results page links the task to its page.
    await page.goto(`${base}/results`);
    check(await page.locator('#per-task a.task-page-link[href="/tasks/T14"]').count() >= 1, 'the Results row of T14 links to its page');

    check(errors.length === 0, `no page errors: ${errors.join('; ')}`);
    say(out);
  } finally {
    await browser.close();
  }
}

main().catch((e) => { say({ ok: false, error: String(e && e.stack || e) }); process.exit(1); });
