// Obstacle avoider (subsumption layer, default priority 3), in JavaScript.
//
// The same component as guest-components/rust/avoider: the same ports,
// parameters, description and commands (tests/all/languages.rs checks it), built
// like it against the contract subsume:robot@0.2.0: `onInput` and `tick`
// return nothing, and a problem goes to `report`.
// Reads a range scan whose rays are spread evenly from -fov/2 (right) to
// +fov/2 (left) of the heading. While an obstacle inside the front cone is
// nearer than `threshold`, it emits `VEL <creep> <turn>` on every tick,
// turning toward the freer side. Otherwise it stays silent: silence tells the
// arbiter this behaviour is not active, so a lower layer drives.
//
// WIT to JavaScript: exports are the module's exported functions, in
// camelCase (on-input -> onInput); a `result` export (`init`) returns
// normally for `ok` and throws the `err` payload; a variant is `{ tag, val }`; an enum is
// its case name as a string; list<f64> arrives as a Float64Array; u64 is a
// BigInt.

import { emit, report } from 'subsume:robot/host@0.2.0';

/** The one instance, made by `init`. */
let state = null;

const numberParam = (name, defaultValue, doc) => ({ name, kind: 'number', defaultValue, doc });

export function describe() {
  return {
    name: 'avoider',
    version: '0.1.0',
    summary: 'Turns away from obstacles nearer than a threshold',
    inputs: [{ name: 'ranges', kind: 'vector', doc: 'ranges in metres, rays from -fov/2 (right) to +fov/2 (left)' }],
    outputs: [{ name: 'cmd', kind: 'command', doc: 'VEL commands while an obstacle is near; silent otherwise' }],
    params: [
      numberParam('threshold', '0.5', 'an obstacle nearer than this (metres) triggers avoidance'),
      numberParam('fov', '3.14159', 'angle covered by the scan, radians'),
      numberParam('cone', '1.6', 'width of the front cone that is watched, radians'),
      numberParam('turn-rate', '1.2', 'turn rate while avoiding, rad/s'),
      numberParam('creep-speed', '0.0', 'forward speed while avoiding, m/s'),
    ],
    defaultPriority: 3,
  };
}

/** Parameter `name` as a number; the host has already checked its kind. */
function number(params, name) {
  const param = params.find((p) => p.name === name);
  if (param === undefined) {
    throw `missing parameter '${name}'`;
  }
  const value = Number(param.value.trim());
  if (Number.isNaN(value)) {
    throw `parameter '${name}': '${param.value}' is not a number`;
  }
  return value;
}

export function init(params) {
  const avoider = {
    threshold: number(params, 'threshold'),
    fov: number(params, 'fov'),
    cone: number(params, 'cone'),
    turnRate: number(params, 'turn-rate'),
    creepSpeed: number(params, 'creep-speed'),
    ranges: [],
  };
  if (avoider.threshold <= 0 || avoider.fov <= 0 || avoider.cone <= 0) {
    throw 'threshold, fov and cone must be positive';
  }
  state = avoider;
}

export function onInput(_port, value) {
  if (state === null) {
    report('on-input called before init');
  } else if (value.tag !== 'vector') {
    report('ranges: expected a vector');
  } else {
    state.ranges = value.val;
  }
}

export function tick(_nowNs) {
  if (state === null) {
    report('tick called before init');
    return;
  }
  const n = state.ranges.length;
  if (n === 0) {
    return;
  }
  const step = n > 1 ? state.fov / (n - 1) : 0;
  let near = false;
  let left = 0;
  let right = 0;
  for (let i = 0; i < n; i++) {
    const r = state.ranges[i];
    const angle = -state.fov / 2 + step * i;
    if (Math.abs(angle) <= state.cone / 2 && r < state.threshold) {
      near = true;
    }
    if (angle > 0) {
      left += r;
    } else if (angle < 0) {
      right += r;
    }
  }
  if (near) {
    const turn = left >= right ? state.turnRate : -state.turnRate;
    emit(0, { tag: 'command', val: `VEL ${fixed(state.creepSpeed, 3)} ${fixed(turn, 3)}` });
  }
}

/**
 * `x` with `digits` decimals, as Rust's `{:.3}`, C's `%.3f` and Python's
 * `:.3f` write it: the exact binary value rounded half to even, a sign for
 * every negative number (-0 too), never an exponent. `toFixed` differs in
 * all three (it rounds ties up and writes 0.000 and 1e+21), so this works
 * on the exact value: x = mantissa * 2^exponent. `x` is finite.
 */
function fixed(x, digits) {
  const bits = new DataView(new ArrayBuffer(8));
  bits.setFloat64(0, x);
  const high = bits.getUint32(0);
  const biased = (high >>> 20) & 0x7ff;
  let mantissa = (BigInt(high & 0xfffff) << 32n) | BigInt(bits.getUint32(4));
  if (biased !== 0) {
    mantissa |= 1n << 52n;
  }
  const exponent = Math.max(biased, 1) - 1075;
  const scaled = mantissa * 10n ** BigInt(digits);
  let n;
  if (exponent >= 0) {
    n = scaled << BigInt(exponent);
  } else {
    const divisor = 1n << BigInt(-exponent);
    n = scaled / divisor;
    const twiceRest = (scaled % divisor) * 2n;
    if (twiceRest > divisor || (twiceRest === divisor && n % 2n === 1n)) {
      n += 1n;
    }
  }
  const text = n.toString().padStart(digits + 1, '0');
  const sign = high >>> 31 ? '-' : '';
  return `${sign}${text.slice(0, -digits)}.${text.slice(-digits)}`;
}
