// The researcher's loop in the portal, in Debian's headless Chromium:
// an upload says while the robot compiles and checks the component, and
// how long that took; the Simulator buttons (pause, step, set pose, reset,
// resume) do what they say, checked against /api/v1/status; a world file
// uploaded shows its located error, or is stored and listed. Screenshots go
// to $ARTIFACTS.
// Usage: node loop.mjs URL USER PASSWORD COMPONENT.wasm
import { check, logIn, openPage, step } from './harness.mjs';

const [url, user, password, wasm] = process.argv.slice(2);
const { browser, page, shot } = await openPage(30000);
const sim = () => page.evaluate(async () => (await (await fetch('/api/v1/status')).json()).sim);
const near = (a, b, tolerance) => Math.abs(a - b) <= tolerance;
try {
  await logIn(page, url, user, password);

  step('upload a component: progress while the robot compiles, then the time it took');
  await page.click('#tabs button[data-tab="components"]');
  // Every text the result line shows, in order.
  await page.evaluate(() => {
    window.uploadTexts = [];
    const line = document.getElementById('upload-result');
    new MutationObserver(() => window.uploadTexts.push(line.textContent)).observe(line, { childList: true, characterData: true, subtree: true });
  });
  await page.setInputFiles('#component-file', wasm);
  await page.fill('#component-name', 'loop-avoider');
  await page.click('#component-upload');
  await page.waitForSelector('#upload-result:has-text("stored \'loop-avoider\'")');
  const texts = await page.evaluate(() => window.uploadTexts);
  const progress = texts.find((t) => /^uploaded 'loop-avoider'; the robot is compiling and checking it\.\.\. \d+ s$/.test(t));
  check(progress, `no compile progress shown: ${JSON.stringify(texts)}`);
  const final = texts[texts.length - 1];
  const took = final.match(/, compiled and checked in (\d+\.\d) s(;|$)/);
  check(took, `no compile time shown: '${final}'`);
  const seconds = Number(await page.getAttribute('#upload-result', 'data-compile-seconds'));
  check(seconds >= 0 && seconds < 300 && Number(took[1]) === Number(seconds.toFixed(1)), `time shown ${took[1]} s, measured ${seconds} s`);
  const stored = await page.evaluate(async () => (await fetch('/api/v1/components/loop-avoider')).status);
  check(stored === 200, `the component is not in the store (${stored})`);
  await shot('loop-1-upload-compiled');

  step('Pause: simulated time stands still');
  await page.click('#tabs button[data-tab="live"]');
  await page.click('#sim-pause');
  await page.waitForSelector('#sim-result:has-text("t = ")');
  const paused = await sim();
  await page.waitForTimeout(600);
  const later = await sim();
  check(later.time_s === paused.time_s && later.x === paused.x, `paused, yet time moved: ${paused.time_s} -> ${later.time_s}`);

  step('Step 0.1 s: time moves by exactly that');
  await page.click('#sim-step');
  await page.waitForFunction((t) => document.getElementById('sim-result').textContent.startsWith(`t = ${t}`), (paused.time_s + 0.1).toFixed(2));
  const stepped = await sim();
  check(near(stepped.time_s, paused.time_s + 0.1, 1e-6), `stepped from ${paused.time_s} to ${stepped.time_s}`);

  step('Set pose: the robot is where the fields say');
  await page.fill('#sim-pose-x', '2');
  await page.fill('#sim-pose-y', '1.5');
  await page.fill('#sim-pose-heading', '0.5');
  await page.click('#sim-pose');
  await page.waitForSelector('#sim-result:has-text("(2.00, 1.50) heading 0.50")');
  const posed = await sim();
  check(posed.x === 2 && posed.y === 1.5 && near(posed.heading, 0.5, 1e-9), `status after set pose: ${JSON.stringify(posed)}`);
  await page.waitForFunction(() => (document.getElementById('map').dataset.robot || '') !== '');
  await shot('loop-2-posed');

  step('Set pose onto the round obstacle: refused, the robot stays');
  await page.fill('#sim-pose-x', '7.2');
  await page.fill('#sim-pose-y', '3');
  await page.click('#sim-pose');
  await page.waitForSelector('#sim-result:has-text("refused: ")');
  const kept = await sim();
  check(kept.x === 2 && kept.y === 1.5, `a refused pose moved the robot: ${JSON.stringify(kept)}`);

  step('Reset: back at the start, time 0');
  await page.click('#sim-reset');
  await page.waitForSelector('#sim-result:has-text("at (1.00, 1.00)")');
  const reset = await sim();
  check(reset.time_s < 0.5 && near(reset.x, 1, 0.05) && near(reset.y, 1, 0.05), `after reset: ${JSON.stringify(reset)}`);

  step('Resume: time runs again');
  await page.click('#sim-resume');
  const resumed = (await sim()).time_s;
  await page.waitForFunction(async (t) => (await (await fetch('/api/v1/status')).json()).sim.time_s > t + 0.3, resumed);
  await shot('loop-3-resumed');

  step('upload a world: a bad one shows its located error, a good one is stored and listed');
  await page.click('#tabs button[data-tab="sets"]');
  const world = (text) => ({ name: 'arena.world', mimeType: 'text/plain', buffer: Buffer.from(text) });
  await page.setInputFiles('#world-file', world('bounds 0 0 10 8\nstart 2 6 0\ngoal 8 1 0.3\nbox 6 3 5 4\n'));
  await page.click('#world-upload');
  await page.waitForSelector('#world-errors li');
  const located = await page.textContent('#world-errors li');
  check(located.startsWith('arena.world:4:1: a box needs X1 > X0 and Y1 > Y0'), `the world's error: '${located}'`);
  await page.setInputFiles('#world-file', world('bounds 0 0 10 8\nstart 2 6 0\ngoal 8 1 0.3\n'));
  await page.click('#world-upload');
  await page.waitForSelector('#world-result:has-text("stored arena.world")');
  await page.waitForSelector('#world-list:has-text("arena.world")');
  check((await page.$$('#world-errors li')).length === 0, 'the old error stayed up');
  await shot('loop-4-world');
  console.log(`ok: compiled and checked in ${took[1]} s; paused at ${paused.time_s.toFixed(2)} s, stepped, posed, reset, resumed`);
} catch (err) {
  await shot('loop-failure').catch(() => {});
  console.error(err);
  process.exitCode = 1;
} finally {
  await browser.close();
}
