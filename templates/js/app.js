// {{name}}: a subsume robot component, made by `subsume new`.
//
// A starting point that already drives a robot: while something within the
// front cone (`cone` radians wide, centred on the heading) is nearer than
// `threshold`, it emits `VEL <creep-speed> <turn>` on every tick, turning
// toward the side whose nearest obstacle is farther; otherwise it stays
// silent, and a lower-priority source drives. Its ports and parameters
// match the demo's obstacle avoider, so it can take that one's place in
// subsume's config/demo.xml.
//
// Built against the contract subsume:robot@0.2.0 (wit/robot.wit). `ranges`
// takes a range scan with its geometry (a simulated robot's serial link
// sends one: each ray's angle is `angleMin + i * angleIncrement`, and
// readings outside `[rangeMin, rangeMax]` are no obstacle), or a plain
// vector of ranges (a filter's output), whose rays are taken as spread
// evenly over `fov` from right to left. `onInput` and `tick` return
// nothing: a problem goes to `report`, and the component keeps running.
//
// WIT to JavaScript: exports are this module's exported functions in
// camelCase (on-input -> onInput, angle-min -> angleMin); `init` returns
// `err` by throwing the message; a variant is `{ tag, val }`; list<f64> is
// a Float64Array; u64 is a BigInt.

import { emit, log, report } from 'subsume:robot/host@0.2.0';

const settings = { threshold: 0.5, fov: Math.PI, cone: 1.6, 'turn-rate': 1.2, 'creep-speed': 0.0 };
// The latest readings as [angle in radians, counter-clockwise from ahead; metres].
let rays = [];

/** Each ray's [angle, range], from a scan's geometry or spread over fov. */
function readings(value) {
  if (value.tag === 'scan') {
    const { angleMin, angleIncrement, rangeMin, rangeMax, ranges } = value.val;
    return Array.from(ranges, (r, i) => [angleMin + i * angleIncrement, r]).filter(([, r]) => r >= rangeMin && r < rangeMax);
  }
  if (value.tag === 'vector') {
    const n = value.val.length;
    const step = n > 1 ? settings.fov / (n - 1) : 0;
    return Array.from(value.val, (r, i) => [-settings.fov / 2 + i * step, r]);
  }
  return null;
}

const number = (name, defaultValue, doc) => ({ name, kind: 'number', defaultValue, doc });

/** Declared once: the host reads it before `init` to check the wiring. */
export function describe() {
  return {
    name: '{{name}}',
    version: '0.1.0',
    summary: 'Turns away from what is close in front',
    inputs: [{ name: 'ranges', kind: 'any', doc: 'a range scan with its geometry, or ranges right to left over fov' }],
    outputs: [{ name: 'cmd', kind: 'command', doc: 'VEL commands while something is close; silent otherwise' }],
    params: [
      number('threshold', '0.5', 'nearer than this in front (metres) is too close'),
      number('fov', '3.14159', 'angle a plain vector of ranges covers, radians (a scan carries its own)'),
      number('cone', '1.6', 'width of the watched front cone, radians'),
      number('turn-rate', '1.2', 'turn rate while turning away, rad/s'),
      number('creep-speed', '0.0', 'forward speed while turning away, m/s'),
    ],
    defaultPriority: 3,
  };
}

/** Every declared parameter arrives, already checked against its kind. */
export function init(params) {
  for (const { name, value } of params) {
    settings[name] = Number(value);
  }
  if (settings.fov <= 0 || settings.cone <= 0) {
    throw 'fov and cone must be positive'; // refuses to start
  }
  log('info', `ready: turning away from anything nearer than ${settings.threshold} m`);
}

export function onInput(_port, value) {
  const seen = readings(value);
  if (seen === null) {
    report(`ranges: expected a scan or a vector, got ${value.tag}`);
    return;
  }
  rays = seen;
}

export function tick(_nowNs) {
  const nearest = (side) => Math.min(Infinity, ...rays.filter(([a]) => side(a)).map(([, r]) => r));
  if (nearest((a) => Math.abs(a) <= settings.cone / 2) < settings.threshold) {
    const turn = nearest((a) => a > 0) >= nearest((a) => a < 0) ? settings['turn-rate'] : -settings['turn-rate'];
    // toFixed rounds like %.3f except on exact ties and -0: fine for a command.
    emit(0, { tag: 'command', val: `VEL ${settings['creep-speed'].toFixed(3)} ${turn.toFixed(3)}` });
  }
}
