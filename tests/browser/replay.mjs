// Replay before activation in Debian's headless Chromium: on the Robot
// files tab, a developer picks a stored recording and clicks a staged set's
// "replay" button; the page shows "identical" for a set whose components
// are those recorded, and the first divergence (time, port, recorded value,
// new value) for a set with a changed component. Values are checked
// against the API's own answer; screenshots go to $ARTIFACTS.
// Usage: node replay.mjs URL USER PASSWORD RECORDING SAME_SET CHANGED_SET
import { check, logIn, openPage, step } from './harness.mjs';

const [url, user, password, recording, sameSet, changedSet] = process.argv.slice(2);
const { browser, page, shot } = await openPage(60000);
const postJson = (p, body) => page.evaluate(async ([p, body]) => {
  const response = await fetch('/api/v1' + p, { method: 'POST', body, headers: { 'content-type': 'application/json' } });
  return response.json();
}, [p, body]);
const resultText = () => page.textContent('#replay-result');
try {
  await logIn(page, url, user, password);

  step('the Robot files tab lists the recording and a replay button per staged set');
  await page.click('#tabs button[data-tab="sets"]');
  await page.waitForSelector(`#replay-recording option[value="${recording}"]`, { state: 'attached' });
  await page.selectOption('#replay-recording', recording);
  for (const id of [sameSet, changedSet]) await page.waitForSelector(`button.replay[data-set="${id}"]`);
  const activeId = String((await page.evaluate(async () => (await fetch('/api/v1/sets')).json())).active);
  check(await page.$(`button.replay[data-set="${activeId}"]`) === null, 'the active set has a replay button');

  step('the set with the recorded components replays identically');
  await page.click(`button.replay[data-set="${sameSet}"]`);
  await page.waitForFunction(() => document.querySelector('#replay-result').dataset.identical !== undefined
    && !document.querySelector('#replay-result').textContent.startsWith('replaying'));
  const same = await resultText();
  check(same.startsWith('identical: set ' + sameSet), `expected identical, shown: ${same}`);
  check(same.includes('filter, avoid, planner'), `the replayed components are not shown: ${same}`);
  check(await page.isHidden('#replay-divergences'), 'a divergence table is shown for an identical replay');
  await shot('replay-1-identical');

  step('the set with a changed planner shows where it first diverges');
  await page.fill('#replay-only', 'planner');
  await page.click(`button.replay[data-set="${changedSet}"]`);
  await page.waitForFunction(() => document.querySelector('#replay-result').dataset.identical === 'false');
  const shown = await resultText();
  const api = await postJson(`/sets/${changedSet}/replay`, JSON.stringify({ recording, only: ['planner'] }));
  check(api.identical === false, `the API says identical: ${JSON.stringify(api)}`);
  const first = api.report.divergences[0];
  check(first.component === 'planner' && first.port === 'cmd', `unexpected first divergence ${JSON.stringify(first)}`);
  const one = (values) => (values.length === 0 ? 'nothing' : JSON.stringify(values.length === 1 ? values[0] : values));
  const expected = `first: planner.cmd at ${first.time_s.toFixed(6)} s (call ${first.call}: ${first.call_kind}): recorded ${one(first.recorded)}, new ${one(first.replayed)}`;
  check(shown.startsWith('diverges: set ' + changedSet), `expected a divergence, shown: ${shown}`);
  check(shown.includes(expected), `shown: ${shown}\nexpected it to include: ${expected}`);
  const rows = await page.$$eval('#replay-divergences tbody tr', (trs) => trs.map((tr) => [...tr.children].map((td) => td.textContent)));
  check(rows.length === api.report.divergences.length, `${rows.length} rows for ${api.report.divergences.length} divergences`);
  check(rows[0][1] === 'planner.cmd' && rows[0][3] === one(first.recorded) && rows[0][4] === one(first.replayed) && rows[0][5] === String(first.calls_differing),
    `the table's first row is ${JSON.stringify(rows[0])}`);
  await shot('replay-2-divergence');

  step('a replay the host refuses says why');
  await page.selectOption('#replay-recording', { index: 0 });
  await page.evaluate(() => {
    const select = document.querySelector('#replay-recording');
    select.append(new Option('rec-1.mcap', 'rec-1.mcap'));
    select.value = 'rec-1.mcap';
  });
  await page.click(`button.replay[data-set="${sameSet}"]`);
  await page.waitForFunction(() => document.querySelector('#replay-result').textContent.includes('was not replayed'));
  const refused = await resultText();
  check(refused.includes('rec-1.mcap'), `the refusal does not name the recording: ${refused}`);
  await shot('replay-3-refused');
  console.log(`ok: identical for set ${sameSet}; set ${changedSet}: ${expected}`);
} catch (err) {
  await shot('replay-failure').catch(() => {});
  console.error(err.stack || String(err));
  process.exitCode = 1;
} finally {
  await browser.close();
}
