// Drives the portal in Debian's headless Chromium: log in, upload a guest,
// see its ports, stage and activate a robot file using it, see it in the
// live view (its Zenoh bridge on the Bridges row), drive with the pad, roll
// back. Screenshots go to $ARTIFACTS.
// Usage: [BRIDGED=1] node portal.mjs URL USER PASSWORD COMPONENT.wasm ROBOT.xml BAD.xml
// Over https, CA_SPKI is the base64 SHA-256 of the test CA's public key:
// Chromium accepts chains through that CA and no other unknown one.
import { chromium } from 'playwright-core';
import path from 'node:path';
import fs from 'node:fs';

const [url, user, password, wasm, robot, bad] = process.argv.slice(2);
const artifacts = process.env.ARTIFACTS || 'browser-artifacts';
// BRIDGED=1: ROBOT.xml publishes the ranges on the Zenoh key browser/ranges
// (checked on the live view's Bridges row, and gone after the rollback).
const bridged = process.env.BRIDGED === '1';
fs.mkdirSync(artifacts, { recursive: true });
const step = (text) => console.log(`step: ${text}`);

const browser = await chromium.launch({
  executablePath: '/usr/bin/chromium',
  args: ['--headless', '--no-sandbox', '--disable-gpu', '--disable-background-networking']
    .concat(process.env.CA_SPKI ? [`--ignore-certificate-errors-spki-list=${process.env.CA_SPKI}`] : []),
});
const page = await browser.newPage({ viewport: { width: 1280, height: 900 } });
page.setDefaultTimeout(20000);
const shot = (name) => page.screenshot({ path: path.join(artifacts, name + '.png'), fullPage: true });
try {
  step('log in');
  await page.goto(url);
  await page.fill('#login-password', 'wrong-password');
  await page.fill('#login-name', user);
  await page.click('#login-button');
  await page.waitForSelector('#login-error:has-text("wrong user name or password")');
  await page.fill('#login-password', password);
  await page.click('#login-button');
  await page.waitForSelector('#tabs:not([hidden])');
  await page.waitForSelector(`#whoami:has-text("${user}")`);
  if (url.startsWith('https:')) {
    step('over https, the session cookie is Secure');
    const cookies = await page.context().cookies();
    const session = cookies.find((c) => c.name === 'subsume_session');
    if (!session || !session.secure || !session.httpOnly) {
      throw new Error(`the session cookie is not Secure and HttpOnly: ${JSON.stringify(session)}`);
    }
    if (await page.evaluate(() => location.protocol) !== 'https:') throw new Error('the page is not on https');
  }

  step('upload a component and see its ports');
  await page.click('#tabs button[data-tab="components"]');
  await page.setInputFiles('#component-file', wasm);
  await page.fill('#component-name', 'browser-avoider');
  await page.click('#component-upload');
  await page.waitForSelector('#upload-result:has-text("stored \'browser-avoider\'")');
  const card = page.locator('.component[data-component="browser-avoider"]');
  await card.waitFor();
  const text = await card.innerText();
  // The upload is the user's own, and the card says how robot files name it.
  const owned = [`${user}/browser-avoider`, 'yours: name it browser-avoider.wasm'];
  for (const words of ['inputs: ranges (vector)', 'outputs: cmd (command)', 'threshold=', ...owned]) {
    if (!text.includes(words)) throw new Error(`component card lacks '${words}': ${text}`);
  }
  await shot('1-component');

  step('a bad robot file shows file:line:column');
  await page.click('#tabs button[data-tab="sets"]');
  await page.setInputFiles('#config-file', bad);
  await page.click('#config-upload');
  await page.waitForSelector(`#config-errors li:has-text("${path.basename(bad)}:")`);
  await shot('2-diagnostics');

  step('stage and activate a robot file that uses it');
  await page.setInputFiles('#config-file', robot);
  await page.click('#config-upload');
  await page.waitForSelector('#config-result:has-text("staged as set")');
  const staged = (await page.innerText('#config-result')).match(/set (\d+)/)[1];
  await page.waitForSelector(`#graph rect[data-component="avoid"]`);
  await shot('3-wiring');
  await page.click(`button.activate[data-set="${staged}"]`);
  await page.waitForSelector(`#set-result:has-text("set ${staged} is active")`);
  await page.waitForSelector(`#set-list tr[data-set="${staged}"] td.status:has-text("active")`);

  step('see it in the live view');
  await page.click('#tabs button[data-tab="live"]');
  await page.waitForSelector(`#active-set:has-text("set ${staged}")`);
  await page.waitForSelector('#health tr[data-component="avoid"] td.running');
  await page.waitForFunction(() => document.querySelector('#pose').textContent.startsWith('x '));
  await page.waitForSelector('#log li');
  if (bridged) {
    step('the Bridges row shows the Zenoh bridge and its counters');
    await page.waitForFunction(() => /^browser\/ranges: peers 0, in 0, out [1-9]\d*, malformed 0, dropped 0, last seen never$/
      .test(document.querySelector('#bridges').textContent));
  }
  await shot('4-live');

  step('drive with the pad');
  await page.click('#tabs button[data-tab="drive"]');
  await page.click('#drive-connect');
  await page.waitForSelector('#drive-status:has-text("rtt")');
  await page.waitForSelector('#drive-status[data-mode="direct"]');
  const pad = page.locator('#pad-left');
  await pad.hover();
  await page.mouse.down();
  await page.waitForTimeout(1500);
  await page.mouse.up();
  const released = await page.evaluate(async () => {
    const status = await (await fetch('/api/v1/status')).json();
    return status.teleop.commands.released;
  });
  if (!(released > 0)) throw new Error(`the pad's commands were not released: ${released}`);
  await shot('5-drive');

  step('roll back to the set that ran before');
  await page.click('#drive-connect');
  await page.click('#tabs button[data-tab="sets"]');
  await page.click('#rollback');
  await page.waitForSelector('#set-result:has-text("rolled back: set")');
  const back = (await page.innerText('#set-result')).match(/set (\d+)/)[1];
  if (back === staged) throw new Error(`rollback kept set ${staged}`);
  await page.click('#tabs button[data-tab="live"]');
  await page.waitForSelector(`#active-set:has-text("set ${back}")`);
  if (bridged) await page.waitForSelector('#bridges:text-is("none")');
  await shot('6-rolled-back');
  console.log(`ok: ${released} pad commands released; rolled back from set ${staged} to set ${back}`);
} catch (err) {
  await shot('failure').catch(() => {});
  console.error(err);
  process.exitCode = 1;
} finally {
  await browser.close();
}
