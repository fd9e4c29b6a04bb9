// {{name}}: a subsume robot component, made by `subsume new`.
//
// A starting point that already drives a robot: while something in the
// middle third of the range scan is nearer than `threshold`, it emits
// `VEL <creep-speed> <turn>` on every tick, turning toward the side with
// more room; otherwise it stays silent, and a lower-priority source drives.
// Its ports and parameters match the demo's obstacle avoider, so it can
// take that one's place in subsume's config/demo.xml.
//
// WIT to JavaScript: exports are this module's exported functions in
// camelCase (on-input -> onInput); to return `err`, throw the message; a
// variant is `{ tag, val }`; list<f64> is a Float64Array; u64 is a BigInt.

import { emit, log } from 'subsume:robot/host@0.1.0';

const settings = { threshold: 0.5, 'turn-rate': 1.2, 'creep-speed': 0.0 };
let ranges = [];

/** Declared once: the host reads it before `init` to check the wiring. */
export function describe() {
  return {
    name: '{{name}}',
    version: '0.1.0',
    summary: 'Turns away from what is close in front',
    inputs: [{ name: 'ranges', kind: 'vector', doc: 'ranges in metres, rays from right to left' }],
    outputs: [{ name: 'cmd', kind: 'command', doc: 'VEL commands while something is close; silent otherwise' }],
    params: [
      { name: 'threshold', kind: 'number', defaultValue: '0.5', doc: 'nearer than this in front (metres) is too close' },
      { name: 'turn-rate', kind: 'number', defaultValue: '1.2', doc: 'turn rate while turning away, rad/s' },
      { name: 'creep-speed', kind: 'number', defaultValue: '0.0', doc: 'forward speed while turning away, m/s' },
    ],
    defaultPriority: 3,
  };
}

/** Every declared parameter arrives, already checked against its kind. */
export function init(params) {
  for (const { name, value } of params) {
    settings[name] = Number(value);
  }
  log('info', `ready: turning away from anything nearer than ${settings.threshold} m`);
}

export function onInput(_port, value) {
  if (value.tag === 'vector') {
    ranges = value.val;
  }
}

export function tick(_nowNs) {
  const third = Math.floor(ranges.length / 3);
  const nearest = (rays) => Math.min(Infinity, ...rays);
  const right = ranges.slice(0, third);
  const front = ranges.slice(third, ranges.length - third);
  const left = ranges.slice(ranges.length - third);
  if (nearest(front) < settings.threshold) {
    const turn = nearest(left) >= nearest(right) ? settings['turn-rate'] : -settings['turn-rate'];
    // toFixed rounds like %.3f except on exact ties and -0: fine for a command.
    emit(0, { tag: 'command', val: `VEL ${settings['creep-speed'].toFixed(3)} ${turn.toFixed(3)}` });
  }
}
