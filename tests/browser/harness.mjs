// What every portal browser test starts with: Debian's headless Chromium
// through playwright-core, one page, and helpers that print steps, fail
// with a message, and save full-page screenshots to $ARTIFACTS.
import { chromium } from 'playwright-core';
import path from 'node:path';
import fs from 'node:fs';

export const step = (text) => console.log(`step: ${text}`);
export const check = (ok, text) => { if (!ok) throw new Error(text); };

// Opens the browser and a 1400x1000 page whose waits time out after
// `timeoutMs`; `shot(name)` saves $ARTIFACTS/name.png (`artifacts`, made
// if missing).
export async function openPage(timeoutMs = 30000) {
  const artifacts = process.env.ARTIFACTS || 'browser-artifacts';
  fs.mkdirSync(artifacts, { recursive: true });
  const browser = await chromium.launch({
    executablePath: '/usr/bin/chromium',
    args: ['--headless', '--no-sandbox', '--disable-gpu', '--disable-background-networking'],
  });
  const page = await browser.newPage({ viewport: { width: 1400, height: 1000 } });
  page.setDefaultTimeout(timeoutMs);
  const shot = (name) => page.screenshot({ path: path.join(artifacts, name + '.png'), fullPage: true });
  return { browser, page, shot, artifacts };
}

// Logs `user` in at the portal's `url` and waits for the tabs.
export async function logIn(page, url, user, password) {
  step('log in');
  await page.goto(url);
  await page.fill('#login-name', user);
  await page.fill('#login-password', password);
  await page.click('#login-button');
  await page.waitForSelector('#tabs:not([hidden])');
}
