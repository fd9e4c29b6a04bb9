// The portal's own views in Debian's headless Chromium: the history plots
// (RTT, message rates, holder), the Drive tab's live map, the wiring as a
// left-to-right data flow with arrows, and the robot-file editor that
// validates as you type and stages what validated, and recording from the
// portal (start, stop, download), and a page opened after the robot ran a
// while plotting the history the host kept at once, the log's line numbers
// past 99, and the header's text while a lock is engaged. Each check reads real
// content (values against /api/v1, pixels of the canvases); screenshots
// go to $ARTIFACTS.
// Usage: node views.mjs URL USER PASSWORD
import path from 'node:path';
import fs from 'node:fs';
import { check, logIn, openPage, step } from './harness.mjs';

const [url, user, password] = process.argv.slice(2);
const { browser, page, shot, artifacts } = await openPage(30000);
const getJson = (p) => page.evaluate(async (p) => (await fetch('/api/v1' + p)).json(), p);
// Pixels of a canvas that are not background, inside a rectangle.
const inked = (id, x0, y0, w, h) => page.evaluate(([id, x0, y0, w, h]) => {
  const data = document.getElementById(id).getContext('2d').getImageData(x0, y0, w, h).data;
  let n = 0;
  for (let i = 0; i < data.length; i += 4) if (data[i + 3] > 0 && (data[i] < 200 || data[i + 1] < 200 || data[i + 2] < 200)) n += 1;
  return n;
}, [id, x0, y0, w, h]);
try {
  await logIn(page, url, user, password);

  step('history plots: message rates and the holder');
  await page.waitForFunction(() => Number(document.querySelector('#plot-rates').dataset.samples || 0) >= 40);
  const status = await getJson('/status');
  const rates = JSON.parse(await page.getAttribute('#plot-rates', 'data-series'));
  for (const c of status.components) check(c.name in rates, `no rate plotted for ${c.name}: ${JSON.stringify(rates)}`);
  // The serial link ticks at 100 Hz and emits ranges and pose each tick.
  // A rate is taken between two status events (5 a second): on a busy
  // machine one such gap can hold no tick, so the plot is watched until
  // its latest sample shows the link running (a link that never ticks
  // never gets there).
  const running = await page.waitForFunction(() => {
    const series = JSON.parse(document.querySelector('#plot-rates').dataset.series || '{}');
    return series.motors > 20 ? series : false;
  }, null, { timeout: 10000 }).then((h) => h.jsonValue(), () => null);
  check(running, `the motors' rate is not plotted as it runs in 10 s: ${await page.getAttribute('#plot-rates', 'data-series')}`);
  check(await inked('plot-rates', 41, 9, 270, 150) > 80, 'the rates plot has no lines');
  const holders = JSON.parse(await page.getAttribute('#plot-holder', 'data-holders'));
  const holderNow = (await getJson('/status')).arbiter.holder || 'STOP';
  check(holders.includes(holderNow), `the holder plot lacks ${holderNow}: ${holders}`);
  check(await inked('plot-holder', 41, 9, 260, 150) > 200, 'the holder plot has no bands');
  await shot('views-1-plots');

  step('the Drive tab shows the live map beside the pad');
  await page.click('#tabs button[data-tab="drive"]');
  await page.waitForFunction(() => document.querySelector('#drive-map').dataset.robot);
  await page.click('#drive-connect');
  await page.waitForSelector('#drive-status[data-mode="direct"]');
  await page.locator('#pad-left').hover();
  await page.mouse.down();
  await page.waitForTimeout(1500);
  await page.mouse.up();
  await page.waitForTimeout(500);
  // Paused, the robot stays where it is: the map must show it there.
  await page.evaluate(async () => { await fetch('/api/v1/sim/pause', { method: 'POST' }); });
  await page.waitForTimeout(800);
  const sim = (await getJson('/status')).sim;
  const map = await page.evaluate(() => {
    const canvas = document.getElementById('drive-map');
    const [x, y] = canvas.dataset.robot.split(',').map(Number);
    const [r, g, b] = canvas.getContext('2d').getImageData(Math.round(x) - 3, Math.round(y) + 3, 1, 1).data;
    return { x, y, r, g, b, rays: Number(canvas.dataset.rays), pose: document.getElementById('drive-pose').textContent };
  });
  check(Math.abs(map.r - 0x0b) + Math.abs(map.g - 0x5c) + Math.abs(map.b - 0xad) < 60, `no robot drawn at ${map.x},${map.y}: ${JSON.stringify(map)}`);
  check(map.rays === sim.ranges.length && map.rays === 9, `rays drawn ${map.rays}, ranges ${sim.ranges.length}`);
  check(map.pose.startsWith(`x ${sim.x.toFixed(2)} y ${sim.y.toFixed(2)} heading ${sim.heading.toFixed(2)}`), `pose shown '${map.pose}', status ${JSON.stringify(sim)}`);
  check(await inked('drive-map', 0, 0, 560, 460) > 1000, 'the map is empty');
  await shot('views-2-drive-map');
  await page.evaluate(async () => { await fetch('/api/v1/sim/resume', { method: 'POST' }); });

  step('the RTT plot shows the operator');
  await page.click('#tabs button[data-tab="live"]');
  await page.waitForFunction((u) => (JSON.parse(document.querySelector('#plot-rtt').dataset.series || '{}')[u] || 0) > 0, user);
  await page.waitForTimeout(3000);
  check(await inked('plot-rtt', 41, 9, 270, 150) > 20, 'the rtt plot has no line');
  await shot('views-3-rtt');
  await page.click('#tabs button[data-tab="drive"]');
  await page.click('#drive-connect');

  step('the wiring flows left to right, with arrows');
  await page.click('#tabs button[data-tab="sets"]');
  const sets = await getJson('/sets');
  const { graph } = await getJson(`/sets/${sets.active}`);
  await page.waitForSelector('#graph .edge');
  const edges = await page.evaluate(() => [...document.querySelectorAll('#graph .edge')].map((e) => ({
    from: e.dataset.from, to: e.dataset.to, back: !!e.dataset.back, marker: e.getAttribute('marker-end'),
    x1: Number(e.getAttribute('x1')), x2: Number(e.getAttribute('x2')),
  })));
  check(edges.length === graph.connections.length, `${edges.length} edges drawn for ${graph.connections.length} connections`);
  for (const c of graph.connections) check(edges.some((e) => e.from === c.from && e.to === c.to), `no edge ${c.from} -> ${c.to}`);
  for (const e of edges) {
    check(e.marker && e.marker.startsWith('url(#arrow'), `edge ${e.from} -> ${e.to} has no arrowhead`);
    if (!e.back) check(e.x2 > e.x1, `edge ${e.from} -> ${e.to} goes right to left`);
  }
  const forward = edges.filter((e) => !e.back).length;
  check(forward >= edges.length - 3, `most edges must flow forward: ${forward} of ${edges.length}`);
  check(await page.locator('#graph marker#arrow path').count() === 1, 'no arrowhead marker');
  const flows = await page.evaluate(() => {
    const x = (name) => Number(document.querySelector(`#graph rect[data-component="${name}"]`).getAttribute('x'));
    return [x('motors'), x('filter'), x('avoid'), x('arbiter'), x('envelope')];
  });
  for (let i = 1; i < flows.length; i += 1) check(flows[i] > flows[i - 1], `not left to right: motors, filter, avoid, arbiter, envelope at ${flows}`);
  await shot('views-4-wiring');

  step('the editor validates as you type, debounced, with subsume check\'s diagnostics');
  let validations = 0;
  page.on('request', (r) => { if (r.url().includes('/validate/')) validations += 1; });
  await page.click('#editor-load');
  await page.waitForSelector('#editor-status.ok:has-text("valid")');
  const original = await page.inputValue('#editor');
  check(original.includes('to="filter.ranges"'), 'the active file was not loaded');
  const bad = original.replace('to="filter.ranges"', 'to="filter.rangez"');
  const badLine = bad.split('\n').findIndex((l) => l.includes('filter.rangez')) + 1;
  await page.fill('#editor', bad);
  const item = page.locator('#editor-diagnostics li').first();
  await item.waitFor();
  const line = Number(await item.getAttribute('data-line'));
  const text = await item.innerText();
  check(line === badLine && /^\d+:\d+: /.test(text) && text.includes('rangez'), `diagnostic '${text}' (line ${line}), the typo is on line ${badLine}`);
  check(await page.isDisabled('#editor-stage'), 'a file with errors may be staged');
  await shot('views-5-editor-error');
  // Ten keys in a burst: one validation after the last, not ten.
  const fixed = original.replace('name="threshold" value="0.55"', 'name="threshold" value="0.6"');
  await page.fill('#editor', fixed);
  await page.waitForSelector('#editor-status.ok');
  validations = 0;
  await page.focus('#editor');
  await page.keyboard.press('Control+End');
  await page.keyboard.type('<!--ok-->\n', { delay: 40 });
  await page.waitForSelector('#editor-status.ok:has-text("changes: control")');
  check(validations >= 1 && validations <= 2, `${validations} validations for a burst of 10 keys`);
  const typed = await page.inputValue('#editor');
  await page.click('#editor-stage');
  await page.waitForSelector('#editor-status:has-text("staged as set")');
  const id = (await page.innerText('#editor-status')).match(/set (\d+)/)[1];
  const stored = await getJson(`/sets/${id}`);
  check(stored.config === typed, 'the staged file is not the text that validated');
  check(stored.status === 'staged' && stored.set.changes.join() === 'control', JSON.stringify(stored.set));
  await page.waitForSelector(`#set-list tr[data-set="${id}"]`);
  await shot('views-6-editor-staged');
  step('record from the portal: start, stop, list, download');
  await page.click('#tabs button[data-tab="recordings"]');
  await page.waitForSelector('#recording-status:has-text("not recording")');
  await page.click('#recording-start');
  await page.waitForSelector('#recording-status:has-text("recording to rec-")');
  const recName = (await page.innerText('#recording-status')).match(/(rec-[\d-]+\.mcap)/)[1];
  await page.waitForSelector(`#recording-list tr[data-name="${recName}"] td:has-text("being written")`);
  await page.waitForTimeout(2000);
  await page.click('#recording-stop');
  await page.waitForSelector(`#recording-status:has-text("stopped ${recName}:")`);
  const messages = Number((await page.innerText('#recording-status')).match(/: (\d+) messages/)[1]);
  check(messages > 200, `only ${messages} messages in 2 s`);
  await page.waitForSelector(`#recording-list tr[data-name="${recName}"] button.delete`);
  const listed = (await getJson('/recordings')).files.find((f) => f.name === recName);
  const [download] = await Promise.all([
    page.waitForEvent('download'),
    page.click(`#recording-list tr[data-name="${recName}"] a`),
  ]);
  const saved = path.join(artifacts, 'views-recording.mcap');
  await download.saveAs(saved);
  const bytes = fs.readFileSync(saved);
  check(bytes.length === listed.bytes, `downloaded ${bytes.length} bytes, listed ${listed.bytes}`);
  // MCAP's magic at both ends: a finished file.
  const magic = Buffer.from([0x89, 0x4d, 0x43, 0x41, 0x50, 0x30, 0x0d, 0x0a]);
  check(bytes.subarray(0, 8).equals(magic) && bytes.subarray(bytes.length - 8).equals(magic), 'the download is not a finished MCAP file');
  await shot('views-7-recordings');

  step('record from a fresh start: the box re-activates the set and says so');
  const auditBefore = (await getJson('/audit?limit=1000')).entries.length;
  await page.check('#recording-fresh');
  await page.click('#recording-start');
  await page.waitForSelector('#recording-status:has-text("from a fresh start")');
  const fresh = await getJson('/recordings');
  check(fresh.recording && fresh.recording.fresh_start === true, `not a fresh-start recording: ${JSON.stringify(fresh.recording)}`);
  const added = (await getJson('/audit?limit=1000')).entries.slice(auditBefore).map((e) => `${e.action} ${e.result}`);
  check(added.includes('activate ok') && added.includes('start-recording ok'), `audit after a fresh start: ${added}`);
  await page.click('#recording-stop');
  await page.waitForSelector(`#recording-status:has-text("stopped ${fresh.recording.name}:")`);
  await page.uncheck('#recording-fresh');
  step('a page opened now plots the history the host kept, at once');
  const opened = Date.now();
  await page.reload();
  await page.waitForSelector('#tabs:not([hidden])');
  await page.waitForFunction(() => document.querySelector('#plot-rates').dataset.history !== undefined);
  const waited = (Date.now() - opened) / 1000;
  const kept = Number(await page.getAttribute('#plot-rates', 'data-history'));
  const span = Number(await page.getAttribute('#plot-rates', 'data-history-span'));
  const hostHistory = await getJson('/history');
  check(kept >= 20 && Math.abs(kept - hostHistory.samples.length) <= 2, `the page drew ${kept} samples of the host's ${hostHistory.samples.length}`);
  // It reaches back before the page was opened: the host's, not the page's.
  check(span > waited + 15, `the plots reach back ${span.toFixed(1)} s, ${waited.toFixed(1)} s after the page opened`);
  const kept_rates = JSON.parse(await page.getAttribute('#plot-rates', 'data-series'));
  check(kept_rates.motors > 20, `the motors' rate is not in the history: ${JSON.stringify(kept_rates)}`);
  check(await inked('plot-rates', 41, 9, 270, 150) > 80, 'the rates plot drew no history');
  check(await inked('plot-holder', 41, 9, 260, 150) > 200, 'the holder plot drew no history');
  await shot('views-8-history');

  step('the log numbers lines past 99 in full, and the header reads while a lock is engaged');
  // 150 lines as the log shows them (the host's own are fewer by now): the
  // number of the last must fit in the room left of its line.
  const numbers = await page.evaluate(() => {
    const log = document.getElementById('log');
    for (let i = log.children.length; i < 150; i += 1) {
      const li = document.createElement('li');
      li.textContent = `12:00:00 INFO filler line ${i + 1}`;
      log.append(li);
    }
    const last = log.lastElementChild;
    const probe = document.createElement('span');
    probe.style.font = getComputedStyle(last).font;
    probe.style.whiteSpace = 'pre';
    probe.textContent = `${log.children.length}. `;
    document.body.append(probe);
    const needed = probe.getBoundingClientRect().width;
    probe.remove();
    return { count: log.children.length, needed, room: last.getBoundingClientRect().left - log.getBoundingClientRect().left };
  });
  check(numbers.room >= numbers.needed, `line ${numbers.count}'s number needs ${numbers.needed.toFixed(1)} px, has ${numbers.room.toFixed(1)}`);
  // WCAG's contrast ratio of each header text against the header.
  const contrasts = () => page.evaluate(() => {
    const rgb = (c) => c.match(/[\d.]+/g).slice(0, 3).map(Number);
    const luminance = (c) => {
      const [r, g, b] = rgb(c).map((v) => { v /= 255; return v <= 0.03928 ? v / 12.92 : ((v + 0.055) / 1.055) ** 2.4; });
      return 0.2126 * r + 0.7152 * g + 0.0722 * b;
    };
    const background = luminance(getComputedStyle(document.querySelector('header')).backgroundColor);
    const texts = [...document.querySelectorAll('header h1, #tabs button, #whoami, #lock-banner')].filter((e) => e.textContent.trim());
    return texts.map((e) => {
      const [a, b] = [luminance(getComputedStyle(e).color), background].sort((x, y) => y - x);
      return { text: e.textContent.trim().slice(0, 20), ratio: (a + 0.05) / (b + 0.05) };
    });
  });
  const readable = (when, list) => {
    const poor = list.filter((c) => c.ratio < 4.5);
    check(list.length >= 6 && poor.length === 0, `${when}, header text below 4.5:1: ${JSON.stringify(poor)}`);
  };
  readable('unlocked', await contrasts());
  await page.click('#estop');
  await page.waitForSelector(`#lock-banner:has-text("estop by ${user} over portal")`);
  readable('locked', await contrasts());
  await shot('views-9-locked-log');
  await page.evaluate(async () => { await fetch('/api/v1/release', { method: 'POST' }); });
  console.log(`ok: ${edges.length} edges, ${validations} validation(s) for a burst, staged set ${id}`);
} catch (err) {
  await shot('views-failure').catch(() => {});
  console.error(err);
  process.exitCode = 1;
} finally {
  await browser.close();
}
