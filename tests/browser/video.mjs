// An experiment bundle's camera video in Debian's headless Chromium
// (tests/all/camera.rs): a page with a <video> of the file plays it to its
// end. Prints one JSON line: duration, size, frames decoded, whether it
// ended, and how many different colours its last frame has (a picture,
// not a blank).
//
// Usage: node video.mjs FILE.webm
import { openPage, step, check } from './harness.mjs';
import path from 'node:path';
import fs from 'node:fs';
import http from 'node:http';

const video = path.resolve(process.argv[2]);
// The page and the video from one origin (a canvas may then read the
// picture): a small HTTP server with byte ranges, as a browser asks.
const bytes = fs.readFileSync(video);
const server = http.createServer((request, response) => {
  if (request.url !== '/video.webm') {
    response.writeHead(200, { 'content-type': 'text/html' });
    response.end('<!doctype html><video id="v" muted playsinline src="/video.webm"></video>');
    return;
  }
  const range = /bytes=(\d+)-(\d*)/.exec(request.headers.range || '');
  if (!range) {
    response.writeHead(200, { 'content-type': 'video/webm', 'content-length': bytes.length, 'accept-ranges': 'bytes' });
    response.end(bytes);
    return;
  }
  const start = Number(range[1]);
  const end = range[2] ? Math.min(Number(range[2]), bytes.length - 1) : bytes.length - 1;
  response.writeHead(206, {
    'content-type': 'video/webm',
    'content-length': end - start + 1,
    'content-range': `bytes ${start}-${end}/${bytes.length}`,
    'accept-ranges': 'bytes',
  });
  response.end(bytes.subarray(start, end + 1));
});
await new Promise((resolve) => server.listen(0, '127.0.0.1', resolve));
const { browser, page, shot } = await openPage(60000);
try {
  step('open the video');
  await page.goto(`http://127.0.0.1:${server.address().port}/`);
  const result = await page.evaluate(() => new Promise((resolve) => {
    const v = document.getElementById('v');
    let finished = false;
    const done = (ended) => {
      if (finished) return;
      finished = true;
      const canvas = document.createElement('canvas');
      canvas.width = v.videoWidth;
      canvas.height = v.videoHeight;
      const context = canvas.getContext('2d');
      context.drawImage(v, 0, 0);
      const pixels = context.getImageData(0, 0, canvas.width, canvas.height).data;
      const colours = new Set();
      for (let i = 0; i < pixels.length; i += 4 * 7) {
        colours.add((pixels[i] >> 4) * 256 + (pixels[i + 1] >> 4) * 16 + (pixels[i + 2] >> 4));
      }
      resolve({
        ended,
        error: v.error ? v.error.message || String(v.error.code) : null,
        duration: v.duration,
        current_time: v.currentTime,
        ready_state: v.readyState,
        width: v.videoWidth,
        height: v.videoHeight,
        frames: v.getVideoPlaybackQuality().totalVideoFrames,
        colours: colours.size,
      });
    };
    v.addEventListener('ended', () => done(true));
    v.addEventListener('error', () => done(false));
    // The metadata may have come before this page's script ran.
    const play = () => {
      v.playbackRate = 4;
      v.play().catch(() => done(false));
    };
    if (v.readyState >= 1) play(); else v.addEventListener('loadedmetadata', play);
    setTimeout(() => done(false), 45000);
  }));
  await shot('video-ended');
  console.log(JSON.stringify(result));
  check(result.error === null, `the video did not play: ${result.error}`);
} finally {
  await browser.close();
  server.close();
}
