// Benchmark helper: an operator logs in to the portal in headless Chromium
// and clicks STOP N times, with a mouse click at the button's centre sent
// as browser input (the way a person's click arrives: through Chromium's
// input pipeline and hit testing, not a script calling the handler). For
// each click it prints "asked MS" (Date.now() just before the mouse input
// is sent) and "clicked MS" (the page's clock when the click event reached
// the document, which is when the portal's own work starts);
// then it waits for the banner, releases with the release button and waits
// for the banner to go. The caller times STOP on the wire against both.
// Usage: node estop-bench.mjs URL USER PASSWORD N
import { chromium } from 'playwright-core';

const [url, user, password, n] = process.argv.slice(2);
const browser = await chromium.launch({
  executablePath: '/usr/bin/chromium',
  args: ['--headless', '--no-sandbox', '--disable-gpu', '--disable-background-networking'],
});
const page = await browser.newPage({ viewport: { width: 1280, height: 900 } });
page.setDefaultTimeout(20000);
page.on('dialog', (dialog) => dialog.accept());
// Say why, when the page goes away mid-run (a renderer crash, a navigation).
page.on('crash', () => console.error('estop-bench: the page crashed'));
page.on('close', () => console.error('estop-bench: the page closed'));
page.on('framenavigated', (frame) => { if (frame === page.mainFrame()) console.error(`estop-bench: navigated to ${frame.url()}`); });
try {
  await page.goto(url);
  await page.fill('#login-name', user);
  await page.fill('#login-password', password);
  await page.click('#login-button');
  await page.waitForSelector('#estop:visible');
  // Capturing on the document runs before the button's own handler.
  await page.evaluate(() => document.addEventListener('click', (event) => {
    if (event.target.id === 'estop') window.clickedAt = performance.timeOrigin + performance.now();
  }, { capture: true }));
  for (let i = 0; i < Number(n); i++) {
    await page.waitForTimeout(250 + (i * 37) % 100);
    // Not page.click: its actionability checks wait for animation frames
    // (about 30 ms here), which a person's click does not.
    const box = await page.locator('#estop').boundingBox();
    console.log(`asked ${Date.now()}`);
    await page.mouse.click(box.x + box.width / 2, box.y + box.height / 2);
    console.log(`clicked ${await page.evaluate(() => window.clickedAt)}`);
    await page.waitForSelector('#lock-banner:has-text("STOPPED")');
    // Release as an operator does (the confirmed button), which refreshes
    // the banner at once; a release behind the page's back left the banner
    // up until the page's timeout, 20 s a sample.
    await page.click('#release');
    await page.waitForFunction(() => !document.querySelector('#lock-banner').textContent.includes('STOPPED'));
  }
  console.log('done');
} catch (err) {
  console.error(String(err));
  await browser.close();
  process.exit(1);
}
await browser.close();
