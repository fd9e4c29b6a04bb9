// Benchmark helper: an operator logs in to the portal in headless Chromium
// and clicks STOP N times; before each click it prints "clicked MS"
// (Date.now()), after each it waits for the banner, then releases through
// the API and waits. The caller times STOP on the wire against MS.
// Usage: node estop-bench.mjs URL USER PASSWORD N
import { chromium } from 'playwright-core';

const [url, user, password, n] = process.argv.slice(2);
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
  await page.waitForSelector('#estop:visible');
  for (let i = 0; i < Number(n); i++) {
    await page.waitForTimeout(250 + (i * 37) % 100);
    console.log(`clicked ${Date.now()}`);
    await page.click('#estop');
    await page.waitForSelector('#lock-banner:has-text("STOPPED")');
    await page.evaluate(() => fetch('/api/v1/release', { method: 'POST', credentials: 'same-origin' }));
    await page.waitForSelector('#lock-banner:not(:has-text("STOPPED"))').catch(() => {});
  }
  console.log('done');
} catch (err) {
  console.error(String(err));
  await browser.close();
  process.exit(1);
}
await browser.close();
