// The lab server's page (web/lab.html, docs/lab.md "Several robots") in
// Debian's headless Chromium, against the real binaries: a user logs in
// and sees every robot the test names, each with its name, profile, state,
// the lab's experiment it runs and its time left (counting down); watches
// a running robot's live status; presses one robot's STOP and sees that
// robot stopped by them, the others not; then STOP ALL, and every robot
// stopped. The submit form shows only to a role that may submit.
// Screenshots go to $ARTIFACTS (labserver-*.png).
// Usage: node labserver.mjs URL USER PASSWORD ROBOTS_JSON
// ROBOTS_JSON: [{"name", "profile", "state", "experiment", "duration_s"}]
// (the first one is stopped alone; `experiment` null when idle).
import { check, openPage, step } from './harness.mjs';

const [url, user, password, robotsJson] = process.argv.slice(2);
const robots = JSON.parse(robotsJson);
const { browser, page, shot } = await openPage(120000);
const row = (name) => `#robots tbody tr[data-robot="${name}"]`;
const cells = (name) => page.$$eval(`${row(name)} td`, (tds) => tds.map((td) => td.textContent));
// Waits until robot `name`'s row satisfies `ok` (its cells' text).
async function waitRow(name, ok, what) {
  const deadline = Date.now() + 120000;
  for (;;) {
    const seen = await cells(name).catch(() => []);
    if (seen.length && ok(seen)) return seen;
    check(Date.now() < deadline, `robot ${name}'s row never showed ${what}: ${JSON.stringify(seen)}`);
    await page.waitForTimeout(200);
  }
}

try {
  step('log in');
  await page.goto(url);
  await page.fill('#login-name', user);
  await page.fill('#login-password', password);
  await page.click('#login-button');
  await page.waitForSelector('#app:not([hidden])');
  await page.waitForSelector('#stop-all:visible');
  const role = (await page.textContent('#whoami')).match(/\((\w+)\)/)[1];
  const submits = ['researcher', 'developer', 'admin'].includes(role);
  check(await page.isVisible('#submit-section') === submits, `a ${role} ${submits ? 'does not see' : 'sees'} the submit form`);

  step('every robot: name, profile, state, experiment, time left');
  const left = {};
  for (const robot of robots) {
    const seen = await waitRow(robot.name, (c) => c[0] === robot.name && c[1] === robot.profile
      && c[2] === robot.state && c[3] === (robot.experiment === null ? '' : String(robot.experiment))
      && (robot.experiment === null ? c[4] === '' : /^\d+ s$/.test(c[4])), JSON.stringify(robot));
    if (robot.experiment !== null) {
      left[robot.name] = parseInt(seen[4], 10);
      check(left[robot.name] > 0 && left[robot.name] <= Math.ceil(robot.duration_s), `time left ${seen[4]}`);
    }
  }
  await shot('labserver-1-robots');
  for (const name of Object.keys(left)) {
    await waitRow(name, (c) => /^\d+ s$/.test(c[4]) && parseInt(c[4], 10) < left[name], 'its time left counting down');
  }

  const first = robots[0];
  step(`watch ${first.name} live`);
  await page.click(`${row(first.name)} button:text-is("watch")`);
  await page.waitForSelector(`#live-view:not([hidden]) #live-robot:text-is("${first.name}")`);
  await page.waitForFunction(() => /^set \d+/.test(document.getElementById('live-status').textContent));
  const live = await page.textContent('#live-status');
  if (first.experiment !== null) check(live.includes('"submitter"'), `no experiment in the live view: ${live.slice(0, 400)}`);
  await shot('labserver-2-live');

  step(`STOP ${first.name}`);
  const stoppedBy = (c) => c[2].startsWith('stopped (') && c[2].includes(`${user}@`);
  await page.click(`${row(first.name)} button:text-is("STOP")`);
  await page.waitForSelector(`#stop-said:has-text("${first.name}: engaged")`);
  await waitRow(first.name, stoppedBy, `stopped by ${user}`);
  for (const other of robots.slice(1)) {
    const seen = await cells(other.name);
    check(!seen[2].startsWith('stopped'), `${other.name} stopped with ${first.name}: ${JSON.stringify(seen)}`);
  }
  await shot('labserver-3-stopped-one');

  step('STOP ALL');
  await page.click('#stop-all');
  for (const robot of robots) {
    await page.waitForSelector(`#stop-said:has-text("${robot.name}: engaged")`);
    await waitRow(robot.name, stoppedBy, `stopped by ${user}`);
  }
  await shot('labserver-4-stopped-all');
  console.log(`ok: ${robots.map((r) => r.name).join(', ')} listed and stopped`);
} catch (err) {
  await shot('labserver-failure').catch(() => {});
  console.error(err);
  process.exitCode = 1;
} finally {
  await browser.close();
}
