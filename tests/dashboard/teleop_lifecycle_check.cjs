// The teleop episode's lifecycle in the console (issue 49, item 4) with Debian's chromium (headless,
// playwright-core), on a server started with a short `--teleop-abandon-s`:
//  - /teleop/TASK opened and left makes no episode;
//  - the first key makes one; "Finish and judge" shows the evaluator's verdict; Reset clears every message;
//  - Abort on the teleop page ends the next one as aborted;
//  - one driven and then left (the page navigates away) is ended as abandoned, and its live page says why;
//  - on the live page of the agent episodes FINISH_ID and ABORT_ID (started, running), "Finish and judge" and Abort.
// Usage: node teleop_lifecycle_check.cjs BASE TASK ABANDON_S FINISH_ID ABORT_ID ARTIFACTS
// Prints one JSON line {"ok":true, ...}. Screenshots go to ARTIFACTS.
const { shotter, check, text, runChecks } = require('./common.cjs');

const [base, task, abandonS, finishId, abortId, artifacts] = process.argv.slice(2);
const shot = shotter(artifacts);

async function hold(page, key, ms) {
  await page.keyboard.down(key);
  await page.waitForTimeout(ms);
  await page.keyboard.up(key);
}

/** Every teleop episode of the server, through the page's own session. */
async function teleopEpisodes(page) {
  const r = await page.request.get(`${base}/api/episodes`);
  const v = await r.json();
  return v.episodes.filter((e) => e.harness === 'teleop');
}

async function episode(page, id) {
  return (await page.request.get(`${base}/api/episodes/${id}`)).json();
}

/** Drives until the page has made its episode and shows its frames; returns the episode id. */
async function drive(page, key) {
  await page.locator('.teleop').focus();
  await hold(page, key, 900);
  await page.locator('#state', { hasText: 'driving' }).waitFor({ timeout: 180000 });
  await page.waitForFunction(() => Number(document.getElementById('frame-count').textContent) >= 2, null, { timeout: 120000 });
  await hold(page, key, 600);
  await page.waitForFunction(() => Number(document.getElementById('acked').textContent) >= 2, null, { timeout: 60000 });
  return text(page, '#episode');
}

runChecks(base, async (context, report, errors) => {
  // 1. Opened and left: no episode.
  let page = await context.newPage();
  page.on('pageerror', (e) => errors.push(`teleop: ${e}`));
  await page.goto(`${base}/teleop/${task}`);
  await page.waitForTimeout(3000);
  report.ready_state = await text(page, '#state');
  check(report.ready_state === 'ready', `an opened page waits for the first input (${report.ready_state})`);
  check((await text(page, '#episode')) === 'no episode yet', 'no episode named');
  await shot(page, 'teleop-ready');
  await page.goto(`${base}/`);
  report.teleop_episodes_after_open_and_leave = (await teleopEpisodes(page)).length;
  check(report.teleop_episodes_after_open_and_leave === 0, `opening /teleop/${task} and leaving made no episode`);

  // 2. The first key makes an episode; Finish and judge shows the verdict.
  await page.goto(`${base}/teleop/${task}`);
  const judged = await drive(page, 'd');
  report.judged_episode = judged;
  check(judged.startsWith('ep-'), `the first key made an episode (${judged})`);
  await page.locator('#finish').click();
  await page.locator('#judged').waitFor({ timeout: 120000 });
  report.judged_text = await text(page, '#judged');
  check(/^(SUCCESS|FAIL)/.test(report.judged_text), `the verdict (${report.judged_text})`);
  report.judged_state = await text(page, '#state');
  const j = await episode(page, judged);
  report.judged_api = { state: j.state, outcome: j.outcome };
  check(j.state === 'finished' && j.outcome === report.judged_text.split(' ')[0], `judged episode in the API: ${JSON.stringify(report.judged_api)}`);
  await shot(page, 'teleop-judged');

  // 3. Reset clears every message of the last episode and makes none until the next input.
  await page.locator('#reset').click();
  await page.locator('#state', { hasText: 'ready' }).waitFor({ timeout: 10000 });
  const cleared = await page.evaluate(() => ({
    result: document.getElementById('save-result').textContent,
    resultHidden: document.getElementById('save-result').classList.contains('hidden'),
    calls: document.getElementById('calls').children.length,
    stages: document.getElementById('stages').children.length,
    episode: document.getElementById('episode').textContent,
    acked: document.getElementById('acked').textContent,
  }));
  report.after_reset = cleared;
  check(cleared.result === '' && cleared.resultHidden && cleared.calls === 0 && cleared.stages === 0, `Reset clears the messages: ${JSON.stringify(cleared)}`);
  check(cleared.episode === 'no episode yet' && cleared.acked === '0', `Reset leaves no episode: ${JSON.stringify(cleared)}`);
  await shot(page, 'teleop-reset');

  // 4. Abort from the teleop page.
  const aborted = await drive(page, 'w');
  check(aborted !== judged, 'a new episode after Reset');
  await page.locator('#abort').click();
  await page.locator('#state', { hasText: 'aborted' }).waitFor({ timeout: 60000 });
  const a = await episode(page, aborted);
  report.aborted_api = { state: a.state, outcome: a.outcome, reason: a.reason };
  check(a.state === 'aborted' && /teleop page/.test(a.reason ?? ''), `aborted from the teleop page: ${JSON.stringify(report.aborted_api)}`);
  await shot(page, 'teleop-aborted');

  // 5. Driven, then left: ended as abandoned after --teleop-abandon-s.
  await page.locator('#reset').click();
  const left = await drive(page, 'a');
  report.abandoned_episode = left;
  await page.goto(`${base}/`);
  const t0 = Date.now();
  let row = await episode(page, left);
  while (row.state !== 'aborted' && Date.now() - t0 < (Number(abandonS) + 60) * 1000) {
    await page.waitForTimeout(500);
    row = await episode(page, left);
  }
  report.abandoned_after_s = (Date.now() - t0) / 1000;
  report.abandoned_api = { state: row.state, outcome: row.outcome, reason: row.reason };
  check(row.state === 'aborted' && /abandoned/.test(row.reason ?? ''), `a page left ends its episode as abandoned: ${JSON.stringify(report.abandoned_api)}`);
  check(report.abandoned_after_s >= Number(abandonS) - 1, `not before ${abandonS} s (${report.abandoned_after_s} s)`);
  await page.goto(`${base}/episodes/${left}`);
  await page.locator('#finished:not(.hidden)').waitFor({ timeout: 30000 });
  report.abandoned_live_reason = await text(page, '#reason');
  check(/abandoned/.test(report.abandoned_live_reason), `the live page says why (${report.abandoned_live_reason})`);
  await shot(page, 'live-abandoned');
  // The home list says why beside the outcome (in full on hover), on the page as served and as pushed live.
  await page.goto(`${base}/`);
  const reasonCell = page.locator(`tr[data-id="${left}"] small.end-reason`);
  await reasonCell.waitFor({ timeout: 30000 });
  report.home_reason = await reasonCell.innerText();
  check(/abandoned/.test(report.home_reason), `the home list names the ending's reason (${report.home_reason})`);
  await shot(page, 'home-abandoned-reason');
  await page.close();

  // 6. The live page of an agent's episode: Finish and judge, and Abort.
  page = await context.newPage();
  page.on('pageerror', (e) => errors.push(`live: ${e}`));
  page.on('dialog', (d) => d.accept(d.defaultValue()));
  await page.goto(`${base}/episodes/${finishId}`);
  await page.locator('#state', { hasText: 'live' }).waitFor({ timeout: 60000 });
  await page.locator('#finish').click();
  await page.locator('#end-result', { hasText: 'judged' }).waitFor({ timeout: 120000 });
  report.live_judged = await text(page, '#end-result');
  check(/^judged: (SUCCESS|FAIL) · stages \d+\/\d+/.test(report.live_judged), `the live page's verdict (${report.live_judged})`);
  await page.locator('#finished:not(.hidden)').waitFor({ timeout: 30000 });
  check(await page.locator('#finish').isDisabled(), 'the buttons are off once the episode ended');
  await shot(page, 'live-judged');
  await page.goto(`${base}/episodes/${abortId}`);
  await page.locator('#state', { hasText: 'live' }).waitFor({ timeout: 60000 });
  await page.locator('#abort').click();
  await page.locator('#end-result', { hasText: 'aborted' }).waitFor({ timeout: 60000 });
  await page.locator('#finished:not(.hidden)').waitFor({ timeout: 30000 });
  const b = await episode(page, abortId);
  report.live_aborted_api = { state: b.state, reason: b.reason };
  check(b.state === 'aborted' && /live page/.test(b.reason ?? ''), `aborted from the live page: ${JSON.stringify(report.live_aborted_api)}`);
  await shot(page, 'live-aborted');
});
