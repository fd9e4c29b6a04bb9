// The Live tab's cameras in Debian's headless Chromium (tests/all/ipcam.rs):
// each user logs in; one who may watch sees each camera's MJPEG stream
// playing in an <img> (a picture of the camera's size, and a newer one
// within 30 s); one who may not sees no camera. Prints one JSON line:
// {USER: {"cameras": N, "width": W, "height": H, "changed": bool}}.
//
// Usage: node cameras.mjs URL PASSWORD USER:watch|none ...
import { openPage, logIn, step, check } from './harness.mjs';

const [url, password, ...users] = process.argv.slice(2);
const results = {};
for (const entry of users) {
  const [user, expect] = entry.split(':');
  const { browser, page, shot } = await openPage(30000);
  try {
    await logIn(page, url, user, password);
    await page.waitForFunction(() => document.getElementById('active-set').textContent.startsWith('set '));
    if (expect === 'watch') {
      step(`${user} sees the camera live`);
      await page.waitForFunction(() => {
        const img = document.querySelector('#cameras img');
        return img && img.complete && img.naturalWidth > 0;
      });
      // A picture the <img> shows, taken in one go once it shows one (a
      // page that replaced the <img> meanwhile would give 0 x 0).
      const picture = async () => (await page.waitForFunction(() => {
        const img = document.querySelector('#cameras img');
        if (!img || !img.complete || img.naturalWidth === 0) return false;
        const canvas = document.createElement('canvas');
        canvas.width = img.naturalWidth;
        canvas.height = img.naturalHeight;
        canvas.getContext('2d').drawImage(img, 0, 0);
        return { width: img.naturalWidth, height: img.naturalHeight, data: canvas.toDataURL() };
      })).jsonValue();
      const heading = async () => page.evaluate(async () => {
        const s = await (await fetch('/api/v1/status')).json();
        return s.sim ? s.sim.heading : null;
      });
      const first = await picture();
      const headingFirst = await heading();
      let later = first;
      let looks = 0;
      // A newer picture within 30 s (a busy machine starves the camera's
      // thread, which runs at a lower priority than the loop), each look
      // after the page painted.
      const until = Date.now() + 30000;
      while (later.data === first.data && Date.now() < until) {
        await page.waitForTimeout(200);
        await page.evaluate(() => new Promise((done) => requestAnimationFrame(() => done())));
        later = await picture();
        looks += 1;
      }
      // What the host said of its camera meanwhile (for a failure's message).
      const camera = later.data === first.data
        ? await page.evaluate(async () => {
          const s = await (await fetch('/api/v1/status')).json();
          return Object.fromEntries(Object.entries(s).filter(([k]) => k.startsWith('camera')));
        })
        : null;
      // Whether the scene changed meanwhile (the robot turns).
      const turned = camera ? [headingFirst, await heading()] : null;
      await shot(`cameras-${user}`);
      const count = await page.evaluate(() => document.querySelectorAll('#cameras img').length);
      const hidden = await page.evaluate(() => document.getElementById('cameras').hidden);
      check(!hidden, `${user}: the cameras are hidden`);
      results[user] = { cameras: count, width: first.width, height: first.height, changed: later.data !== first.data, looks, camera, turned };
    } else {
      step(`${user} sees no camera`);
      await page.waitForTimeout(1500);
      await shot(`cameras-${user}`);
      const count = await page.evaluate(() => document.querySelectorAll('#cameras img').length);
      const hidden = await page.evaluate(() => document.getElementById('cameras').hidden);
      results[user] = { cameras: count, hidden };
    }
  } finally {
    await browser.close();
  }
}
console.log(JSON.stringify(results));
