// A test component for the hostile-component suite (tests/all/hostile.rs).
//
// The obstacle avoider's shape (a `ranges` input, a `cmd` output, priority
// 3) that drives (`VEL 0.3 0` on every tick) for `after` ticks and then
// waits 10 s in `tick` the way JavaScript can, chosen by `mode`:
// - `busy-wait`: spins until `Date.now()` has moved 10 s on (JavaScript has
//   no synchronous sleep; this is what one writes instead);
// - `timeout`: schedules the next command 10 s ahead with `setTimeout` and
//   returns.
// The host must not let either hold the control loop.

import { emit } from 'subsume:robot/host@0.1.0';

let after = 10;
let mode = 'busy-wait';
let ticks = 0;

export function describe() {
  return {
    name: 'test-sleeper',
    version: '0.1.0',
    summary: 'Drives, then waits 10 s in tick (for the hostile-component tests)',
    inputs: [{ name: 'ranges', kind: 'vector', doc: 'ignored' }],
    outputs: [{ name: 'cmd', kind: 'command', doc: 'VEL 0.3 0 on every tick before the wait' }],
    params: [
      { name: 'after', kind: 'integer', defaultValue: '10', doc: 'ticks that drive before the wait' },
      { name: 'mode', kind: 'text', defaultValue: 'busy-wait', doc: 'busy-wait or timeout' },
    ],
    defaultPriority: 3,
  };
}

export function init(params) {
  for (const p of params) {
    if (p.name === 'after') {
      after = Number(p.value.trim());
    } else if (p.name === 'mode') {
      mode = p.value.trim();
    }
  }
}

export function onInput(_port, _value) {}

const drive = () => emit(0, { tag: 'command', val: 'VEL 0.3 0' });

export function tick(_nowNs) {
  ticks += 1;
  if (ticks > after) {
    if (mode === 'timeout') {
      setTimeout(drive, 10000);
      return;
    }
    const end = Date.now() + 10000;
    while (Date.now() < end) {
      // spin
    }
  }
  drive();
}
