// The Lab tab in Debian's headless Chromium, against the real binary: a
// researcher sees the Lab tab and the watch views but no activate,
// rollback, replay, recording or drive controls; stages a set and submits
// two experiments while an admin has paused the queue; sees them queued
// with their places, then (the admin resumes) the first running with its
// time left, the second with its ETA, the live map, and the banner on
// another tab (with the stop button; a viewer's banner has none); the
// first goes through checking, preflight, queued, running, finishing and
// done; the banner's stop cancels the second; the first's results download
// as a tar. Refusals show their reason: a duration over the maximum (400),
// a broken robot file's diagnostics as file:line:column (422), a preflight
// that finds the robot held at its geofence (refused, with the reason), a
// daily limit with when it frees (429). The admin sees every experiment,
// edits the settings, books for nobody but sees the researcher's
// reservation (booked and cancelled by her), confirms a manual reset, and
// marks a baseline. Screenshots go to $ARTIFACTS; the results tar is
// saved there as lab-results.tar.
// Usage: node lab.mjs URL ADMIN RESEARCHER VIEWER PASSWORD MINE.xml BROKEN.xml REVERSE.xml
import path from 'node:path';
import { check, logIn, openPage, step } from './harness.mjs';

const [url, adminName, researcher, viewerName, password, mine, broken, reverse] = process.argv.slice(2);
const { browser, page: ana, artifacts } = await openPage(60000);
const newPage = async () => {
  const page = await browser.newPage({ viewport: { width: 1400, height: 1000 } });
  page.setDefaultTimeout(60000);
  return page;
};
const admin = await newPage();
const viewer = await newPage();
const shotOf = (page, name) => page.screenshot({ path: path.join(artifacts, name + '.png'), fullPage: true });
const getJson = (page, p) => page.evaluate(async (p) => (await fetch('/api/v1' + p)).json(), p);
const visible = (page, selector) => page.isVisible(selector);
const card = (id) => `#lab-experiments .experiment[data-experiment="${id}"]`;
const tab = (page, name) => page.click(`#tabs button[data-tab="${name}"]`);
// Submits from the Lab tab; returns the experiment's id.
async function submit(set, duration, label) {
  await ana.selectOption('#lab-set', String(set));
  await ana.fill('#lab-duration', String(duration));
  await ana.fill('#lab-label', label);
  await ana.click('#lab-submit');
  await ana.waitForSelector('#lab-submit-result[data-experiment]');
  return Number(await ana.getAttribute('#lab-submit-result', 'data-experiment'));
}
// The refusal shown after submitting with the form as filled.
async function refusal() {
  await ana.click('#lab-submit');
  await ana.waitForSelector('#lab-submit-result.error');
  return ana.textContent('#lab-submit-result');
}
async function saveSettings(change) {
  await change();
  await admin.click('#lab-settings-save');
  await admin.waitForSelector('#lab-settings-result.ok:has-text("saved")');
}

try {
  await logIn(admin, url, adminName, password);
  await logIn(ana, url, researcher, password);
  await logIn(viewer, url, viewerName, password);

  step('each role sees only the controls it may use');
  for (const t of ['live', 'lab', 'components', 'sets']) check(await visible(ana, `#tabs button[data-tab="${t}"]`), `the researcher has no ${t} tab`);
  // Outside a reservation of her own she may not drive: no Drive tab.
  for (const t of ['drive', 'recordings']) check(!(await visible(ana, `#tabs button[data-tab="${t}"]`)), `the researcher sees the ${t} tab`);
  check(!(await visible(ana, '#sim-controls')), 'the researcher sees the simulator controls');
  check(!(await visible(viewer, '#tabs button[data-tab="lab"]')), 'the viewer sees the Lab tab');
  check(!(await visible(viewer, '#config-upload-section')) && !(await visible(viewer, '#rollback')), 'the viewer sees staging or rollback');
  await tab(admin, 'sets');
  check(await visible(admin, '#rollback') && await visible(admin, '#replay-section'), 'the admin lacks rollback or replay');
  await tab(admin, 'drive');
  check(await visible(admin, '#pad'), 'the admin cannot drive from the Drive tab');

  step('inside her own reservation the researcher may drive: the pad shows and connects; cancelled, it goes');
  await tab(ana, 'lab');
  await ana.evaluate(() => {
    const now = new Date();
    document.getElementById('lab-book-start').value = new Date(now.getTime() - now.getTimezoneOffset() * 60000).toISOString().slice(0, 16);
  });
  await ana.fill('#lab-book-minutes', '15');
  await ana.click('#lab-book');
  await ana.waitForSelector('#lab-book-result.ok:has-text("booked reservation")');
  const now = (await ana.textContent('#lab-book-result')).match(/reservation (\d+)/)[1];
  await ana.waitForSelector(`#lab-reservations tr.now[data-reservation="${now}"]`);
  await ana.waitForSelector('#tabs button[data-tab="drive"]');
  await tab(ana, 'drive');
  await ana.waitForSelector('#pad');
  await ana.click('#drive-connect');
  await ana.waitForSelector('#drive-status:has-text("rtt")');
  await shotOf(ana, 'lab-0-researcher-reserved');
  await ana.click('#drive-connect');
  await tab(ana, 'lab');
  await ana.click(`#lab-reservations button.unbook[data-reservation="${now}"]`);
  await ana.waitForSelector(`#lab-reservations tr[data-reservation="${now}"]`, { state: 'detached' });
  await ana.waitForSelector('#tabs button[data-tab="drive"]', { state: 'hidden' });
  await ana.waitForFunction(() => document.getElementById('drive-pad-column').hidden);

  step('the researcher stages a robot file the way the portal always did');
  await tab(ana, 'sets');
  check(!(await visible(ana, '#rollback')) && !(await visible(ana, '#replay-section')), 'the researcher sees rollback or replay');
  await ana.setInputFiles('#config-file', mine);
  await ana.click('#config-upload');
  await ana.waitForSelector('#config-result:has-text("staged as set")');
  const set = Number((await ana.textContent('#config-result')).match(/set (\d+)/)[1]);
  await ana.waitForSelector(`#set-list tr[data-set="${set}"] button.activate`, { state: 'attached' });
  check(!(await visible(ana, `#set-list tr[data-set="${set}"] button.activate`)), 'the researcher is offered activate');

  step('the admin pauses the queue');
  await tab(admin, 'lab');
  await admin.waitForSelector('#lab-admin');
  await admin.click('#lab-pause');
  await admin.waitForSelector('#lab-queue-state:text-is("paused")');
  check(await admin.isDisabled('#lab-pause') && !(await admin.isDisabled('#lab-resume')), 'pause and resume buttons do not follow the state');

  step('the researcher submits two experiments; they wait, each with its place');
  await tab(ana, 'lab');
  check(!(await visible(ana, '#lab-admin')), 'the researcher sees the admin section');
  check(await ana.textContent('#lab-experiments-title') === 'My experiments', 'the researcher\'s list is not titled hers');
  // The list is drawn when the tab opens (a request): wait for it.
  const ownFirst = await ana.waitForFunction((v) => document.querySelector('#lab-set').options[0]?.value === v,
    String(set), { timeout: 10000 }).then(() => true, () => false);
  check(ownFirst, 'the researcher\'s own set is not offered first');
  // Every state each experiment card shows, in order, as the page draws it.
  await ana.evaluate(() => {
    window.seen = {};
    const note = () => {
      for (const c of document.querySelectorAll('#lab-experiments .experiment')) {
        const states = (window.seen[c.dataset.experiment] ||= []);
        if (states[states.length - 1] !== c.dataset.state) states.push(c.dataset.state);
      }
    };
    new MutationObserver(note).observe(document.getElementById('lab-experiments'), { childList: true, subtree: true });
  });
  const first = await submit(set, 8, 'first try');
  const second = await submit(set, 20, 'second try');
  for (const [id, place] of [[first, 1], [second, 2]]) {
    await ana.waitForSelector(`${card(id)}[data-state="queued"] .place:text-is("place ${place} in the queue")`);
    check((await ana.textContent(`${card(id)} .exp-now`)).includes('the queue is paused'), `experiment ${id} does not say the queue is paused`);
  }
  await shotOf(ana, 'lab-1-queued');

  step('the admin sees every experiment, with its submitter, and resumes');
  await admin.waitForSelector(`${card(second)}[data-state="queued"]`);
  check(await admin.textContent('#lab-experiments-title') === 'Every experiment', 'the admin\'s list is not every experiment');
  check((await admin.innerText(`${card(first)} .exp-meta`)).includes(`by ${researcher}`), 'the admin does not see the submitter');
  check(!(await visible(ana, `${card(first)} .lab-submitter`)), 'the researcher is told her own name');
  await admin.click('#lab-resume');
  await admin.waitForSelector('#lab-queue-state:text-is("runs")');

  step('the first runs with its time left, the second waits with its ETA; the live map is drawn');
  await ana.waitForSelector(`${card(first)}[data-state="running"]`);
  await ana.waitForSelector(`${card(second)} .eta`);
  const running = (await getJson(ana, `/experiments/${first}`)).experiment;
  const eta = Number(await ana.getAttribute(`${card(second)} .eta`, 'data-eta'));
  // The ETA is the first's end plus the turnaround (lab::TURNAROUND, 1 s).
  check(eta === running.ends_unix_ms + 1000, `ETA ${eta}, the first ends at ${running.ends_unix_ms}`);
  check(/^place 1 in the queue; starts about .+ \(in \d+ s\)$/.test(await ana.innerText(`${card(second)} .exp-now`)), await ana.innerText(`${card(second)} .exp-now`));
  check(/on the robot: \d+ s left/.test(await ana.innerText(`${card(first)} .exp-now`)), 'the running experiment has no time left');
  await ana.waitForSelector('#lab-live');
  await ana.waitForFunction(() => document.getElementById('lab-map').dataset.robot);
  check((await ana.textContent('#lab-live-title')).includes(`experiment ${first} by ${researcher}`), 'the live view does not name the experiment');
  await shotOf(ana, 'lab-2-running');

  step('every tab shows the banner: who, which set, the time left; a stop button for the submitter and admins only');
  await tab(ana, 'live');
  const bannerText = `Experiment ${first} 'first try' by ${researcher} runs set ${set}:`;
  await ana.waitForSelector(`#lab-banner:has-text("${bannerText}")`);
  check(/\d+ s left$/.test((await ana.textContent('#lab-banner-text')).trim()), await ana.textContent('#lab-banner-text'));
  check(await visible(ana, '#lab-banner-stop'), 'the submitter has no stop button');
  // Whose code drives: the live view names the experiment and each WASM
  // component's sha256 (the record's).
  await ana.waitForSelector(`#experiment-tag:text-is("experiment ${first} by ${researcher} ('first try')")`);
  for (const c of running.components.filter((c) => c.sha256)) {
    await ana.waitForSelector(`#health tr[data-component="${c.name}"] td.sha[title="${c.sha256}"]`);
  }
  await shotOf(ana, 'lab-3-banner');
  // A viewer sees that it runs, by whom and until when; its label is the
  // submitter's and the admins' (docs/portal.md, "Who sees what").
  await tab(viewer, 'components');
  await viewer.waitForSelector(`#lab-banner:has-text("Experiment ${first} by ${researcher} runs set ${set}:")`);
  check(!(await visible(viewer, '#lab-banner-stop')), 'a viewer may stop someone\'s experiment');
  await admin.waitForSelector(`#lab-banner:has-text("${bannerText}")`);
  check(await visible(admin, '#lab-banner-stop'), 'the admin has no stop button');

  step('the researcher books a window; the admin sees it; she cancels it');
  await tab(ana, 'lab');
  check(!(await visible(ana, '#lab-book-for')), 'the researcher may book for others');
  await ana.fill('#lab-book-minutes', '20');
  await ana.click('#lab-book');
  await ana.waitForSelector('#lab-book-result.ok:has-text("booked reservation")');
  const booked = (await ana.textContent('#lab-book-result')).match(/reservation (\d+)/)[1];
  await admin.waitForSelector(`#lab-reservations tr[data-reservation="${booked}"]:has-text("${researcher}")`);
  await ana.click(`#lab-reservations button.unbook[data-reservation="${booked}"]`);
  await ana.waitForSelector(`#lab-reservations tr[data-reservation="${booked}"]`, { state: 'detached' });

  step('the first ends done, having passed every state');
  await ana.waitForSelector(`${card(first)}[data-state="done"]`);
  const timeline = await ana.$$eval(`${card(first)} .timeline li`, (items) => items.map((i) => i.dataset.state));
  check(timeline.join() === 'checking,preflight,queued,running,finishing,done', `timeline ${timeline}`);
  check((await ana.textContent(`${card(first)} .preflight`)).startsWith('Preflight: passed'), 'no preflight verdict');
  check((await ana.textContent(`${card(first)} .run`)).startsWith('On the robot: 8.'), await ana.textContent(`${card(first)} .run`));
  const seen = await ana.evaluate((id) => window.seen[id], first);
  const live = ['queued', 'running', 'done'];
  check(live.every((s) => seen.includes(s)) && live.map((s) => seen.indexOf(s)).every((i, k, a) => k === 0 || a[k - 1] < i), `seen live: ${seen}`);

  step('the second runs; the banner\'s stop cancels it and the robot goes back');
  await tab(ana, 'live');
  await ana.waitForSelector(`#lab-banner:has-text("Experiment ${second} 'second try'")`);
  await ana.click('#lab-banner-stop');
  await ana.waitForSelector('#lab-banner', { state: 'hidden' });
  await tab(ana, 'lab');
  await ana.waitForSelector(`${card(second)}[data-state="cancelled"] .reasons li:has-text("cancelled by ${researcher}")`);

  step('the first\'s results download as one tar');
  const [download] = await Promise.all([ana.waitForEvent('download'), ana.click(`${card(first)} a.results`)]);
  check(download.suggestedFilename() === `experiment-${first}.tar`, download.suggestedFilename());
  await download.saveAs(path.join(artifacts, 'lab-results.tar'));

  step('a duration over the maximum is refused with its reason');
  await ana.selectOption('#lab-set', String(set));
  await ana.fill('#lab-duration', '1000');
  const tooLong = await refusal();
  check(tooLong.includes(`set ${set} was not submitted (400): duration_s must be from 1 to the robot's max-duration of 120 s, got 1000`), tooLong);

  step('a broken robot file shows file:line:column');
  await ana.setInputFiles('#lab-robot', broken);
  await ana.fill('#lab-duration', '5');
  const invalid = await refusal();
  check(invalid.includes(`${path.basename(broken)} was not staged, nothing was submitted (422)`), invalid);
  const diagnostic = await ana.textContent('#lab-submit-errors li');
  check(new RegExp(`^${path.basename(broken)}:\\d+:\\d+: .*arbiter`).test(diagnostic), diagnostic);

  step('a robot file whose robot backs into the geofence is staged, submitted and refused by its preflight');
  await ana.setInputFiles('#lab-robot', reverse);
  await ana.fill('#lab-duration', '10');
  await ana.fill('#lab-label', 'reverse');
  await ana.click('#lab-submit');
  await ana.waitForSelector('#lab-submit-result.ok:has-text("staged reverse.xml as set")');
  const refused = Number(await ana.getAttribute('#lab-submit-result', 'data-experiment'));
  await ana.waitForSelector(`${card(refused)}[data-state="refused"]`);
  const reason = await ana.textContent(`${card(refused)} .reasons li`);
  check(reason.startsWith('preflight: ') && reason.includes("'reverse' held control"), reason);
  check((await ana.textContent(`${card(refused)} .preflight`)).startsWith('Preflight: did not pass'), 'no refusing verdict');
  await ana.click(`${card(refused)} summary`);
  await shotOf(ana, 'lab-4-refused');

  step('over the daily robot minutes: 429, with when it frees');
  await tab(admin, 'lab');
  {
    // The admin sees every user's sets; her form offers her own or the
    // baseline, never another user's staged set.
    await admin.waitForFunction(() => document.querySelector('#lab-set').options.length > 1);
    const chosen = await admin.$eval('#lab-set', (s) => s.value);
    const { sets } = await getJson(admin, '/sets');
    const { baseline } = (await getJson(admin, '/lab')).lab;
    const picked = sets.find((x) => String(x.id) === chosen);
    check(chosen === '' || (picked && (picked.created_by === adminName || picked.id === baseline)),
      `the admin's form preselects set ${chosen}, someone else's`);
  }
  await saveSettings(() => admin.fill('#lab-setting-limits-robot-minutes-per-day', '0.2'));
  check((await getJson(admin, '/lab')).lab.settings.limits.robot_minutes_per_day === 0.2, 'the setting was not stored');
  await ana.selectOption('#lab-set', String(set));
  await ana.fill('#lab-duration', '10');
  const limited = await refusal();
  check(limited.includes('(429): ') && limited.includes('robot-minutes') && /You may submit again at .+ \(in \d+ (s|min|h)/.test(limited), limited);
  await shotOf(ana, 'lab-5-limit');

  step('a manual reset: the next experiment waits until an admin confirms');
  await saveSettings(async () => {
    await admin.fill('#lab-setting-limits-robot-minutes-per-day', '30');
    await admin.selectOption('#lab-setting-reset', 'manual');
  });
  const third = await submit(set, 3, 'after a reset');
  await admin.waitForSelector('#lab-reset-wait:has-text("Experiment ' + third + ' is next")');
  await ana.waitForSelector(`${card(third)} .exp-now:has-text("waits for the robot to be reset")`);
  check(!(await visible(ana, '#lab-reset-confirm')), 'the researcher may confirm a reset');
  await shotOf(admin, 'lab-6-admin');
  await admin.click('#lab-reset-confirm');
  await ana.waitForSelector(`${card(third)}[data-state="done"]`, { timeout: 60000 });

  step('the admin marks the researcher\'s set as the baseline');
  await admin.selectOption('#lab-baseline-set', String(set));
  await admin.click('#lab-baseline-mark');
  await admin.waitForSelector(`#lab-baseline-result.ok:has-text("set ${set} is the baseline")`);
  await admin.waitForSelector(`#lab-baseline:text-is("set ${set}")`);
  check((await getJson(admin, '/lab')).lab.baseline === set, 'the baseline was not stored');
  await ana.waitForSelector(`#lab-state:has-text("the baseline is set ${set}")`);
  await shotOf(admin, 'lab-7-baseline');
  console.log(`ok: set ${set}; done ${first}, cancelled ${second}, refused ${refused}, after a reset ${third}`);
} catch (err) {
  for (const [name, page] of [['ana', ana], ['admin', admin], ['viewer', viewer]]) await shotOf(page, `lab-failure-${name}`).catch(() => {});
  console.error(err);
  process.exitCode = 1;
} finally {
  await browser.close();
}
