// The portal's STOP button in headless Chromium: a viewer logs in, goes to
// a tab other than the live view, clicks STOP and sees who stopped the
// robot; a viewer is offered no release. Prints "clicked AT_MS" (Date.now()
// just before the click) so the caller can time STOP on the wire.
// Usage: node estop.mjs URL USER PASSWORD
import { chromium } from 'playwright-core';

const [url, user, password] = process.argv.slice(2);
const browser = await chromium.launch({
  executablePath: '/usr/bin/chromium',
  args: ['--headless', '--no-sandbox', '--disable-gpu', '--disable-background-networking'],
});
const page = await browser.newPage({ viewport: { width: 1280, height: 900 } });
page.setDefaultTimeout(20000);
try {
  await page.goto(url);
  await page.fill('#login-name', user);
  await page.fill('#login-password', password);
  await page.click('#login-button');
  await page.waitForSelector('#tabs:not([hidden])');
  await page.click('#tabs button[data-tab="components"]');
  await page.waitForSelector('#estop:visible');
  console.log(`clicked ${Date.now()}`);
  await page.click('#estop');
  await page.waitForSelector(`#lock-banner:has-text("estop by ${user} over portal")`);
  if (await page.isVisible('#release')) throw new Error('a viewer is offered the release');
  console.log('ok: stopped from the browser');
} catch (err) {
  console.error(String(err));
  await browser.close();
  process.exit(1);
}
await browser.close();
