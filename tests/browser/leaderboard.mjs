// The owner's task in the Lab tab, in Debian's headless Chromium against
// the real binary: a researcher whose run was scored sees its score on its
// card (with the preflight's beside it) and the task's leaderboard with
// her own name, rank 1, the value the API gives and the recording's
// sha256; another researcher sees the same board with her as a
// pseudonym, no experiment id. A run scored by a scoring component shows
// the component's sha256, its sub-scores and the built-in metrics beside
// them. Screenshots go to $ARTIFACTS.
// Usage: node leaderboard.mjs URL OWNER OTHER PASSWORD EXPERIMENT
import path from 'node:path';
import { check, logIn, openPage, step } from './harness.mjs';

const [url, owner, other, password, experiment] = process.argv.slice(2);
const { browser, page: mine, artifacts } = await openPage(60000);
const theirs = await browser.newPage({ viewport: { width: 1400, height: 1000 } });
theirs.setDefaultTimeout(60000);
const shotOf = (page, name) => page.screenshot({ path: path.join(artifacts, name + '.png'), fullPage: true });
const getJson = (page, p) => page.evaluate(async (p) => (await fetch('/api/v1' + p)).json(), p);

try {
  await logIn(mine, url, owner, password);
  await logIn(theirs, url, other, password);
  for (const page of [mine, theirs]) await page.click('#tabs button[data-tab="lab"]');

  step('the run\'s card shows its score, apart from its state');
  const card = `#lab-experiments .experiment[data-experiment="${experiment}"]`;
  await mine.waitForSelector(`${card}[data-state="done"] .score`);
  const { experiment: record } = await getJson(mine, `/experiments/${experiment}`);
  const scoreText = await mine.textContent(`${card} .score`);
  check(scoreText.includes(`Score: task ${record.score.task}: ${record.score.metric}`), `the card says: ${scoreText}`);
  check(scoreText.includes("the preflight's"), `no preflight score on the card: ${scoreText}`);
  // Each sub-score as the API gives it; a scoring component's sha256 and
  // the built-in metrics beside its sub-scores.
  const shown = (v) => String(Math.round(v * 1000) / 1000);
  const subText = await mine.textContent(`${card} .sub-scores`);
  for (const [name, v] of Object.entries(record.score.sub_scores)) {
    check(subText.includes(`${name} ${shown(v)}`), `the card lacks sub-score ${name} ${shown(v)}: ${subText}`);
  }
  if (record.score.scorer_sha256) {
    const scorer = await mine.getAttribute(`${card} .scorer`, 'title');
    check(scorer === record.score.scorer_sha256, `the card names scorer ${scorer}, the record ${record.score.scorer_sha256}`);
    const builtText = await mine.textContent(`${card} .built-in`);
    for (const name of ['path_length_m', 'goal_reached', 'energy']) {
      check(builtText.includes(`${name} ${shown(record.score.built_in[name])}`), `the card lacks ${name}: ${builtText}`);
    }
  }

  step('the leaderboard: her run first, under her name');
  const { lab } = await getJson(mine, '/lab');
  check(lab.task && lab.task.name === record.score.task, `the lab view names no task: ${JSON.stringify(lab.task)}`);
  await mine.waitForSelector('#lab-board:not([hidden]) #lab-board-table tr[data-rank="1"]');
  const { leaderboard } = await getJson(mine, `/tasks/${lab.task.name}/leaderboard`);
  const first = leaderboard.entries[0];
  const row = '#lab-board-table tr[data-rank="1"]';
  const user = await mine.textContent(`${row} .user`);
  check(user === `${owner} (experiment ${experiment})`, `her row names ${user}`);
  const value = Number(await mine.textContent(`${row} .value`));
  check(Math.abs(value - first.value) < 0.001, `the page shows ${value}, the API ${first.value}`);
  const sha = await mine.getAttribute(`${row} .sha`, 'title');
  check(sha === first.recording_sha256 && sha.length === 64, `the recording's sha256: ${sha}`);
  check((await mine.getAttribute(row, 'class')) === 'yours', 'her row is not marked hers');
  check((await mine.textContent('#lab-board-title')) === `Leaderboard: ${lab.task.name}`, 'the board\'s title');
  await shotOf(mine, 'leaderboard-0-owner');

  step('another researcher sees a pseudonym and no experiment id');
  await theirs.waitForSelector('#lab-board:not([hidden]) #lab-board-table tr[data-rank="1"]');
  const seen = await theirs.textContent('#lab-board-table tr[data-rank="1"] .user');
  check(seen === 'participant-1', `the other researcher sees ${seen}`);
  check(!(await theirs.textContent('#lab-board')).includes(owner), 'the owner\'s name shows on the other\'s board');
  await shotOf(theirs, 'leaderboard-1-other');
  console.log(`ok: experiment ${experiment} ranked 1 at ${first.value}`);
} catch (err) {
  for (const [name, page] of [['mine', mine], ['theirs', theirs]]) await shotOf(page, `leaderboard-failure-${name}`).catch(() => {});
  console.error(err);
  process.exitCode = 1;
} finally {
  await browser.close();
}
